"""Infrastructure: atomic files, settings, TOML/JSON reading, threads, executors."""
