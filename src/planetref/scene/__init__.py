"""The scene: its manifest (``scene.toml``), its inputs opened and checked, and ``scene init``."""
