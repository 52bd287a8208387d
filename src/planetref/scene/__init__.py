"""The scene: its manifest (``scene.toml``) and its inputs, opened and checked."""
