"""Scenes: what a run is given (manifest, inputs) and how a scene is made from files."""
