"""The end-to-end pipeline: georef, compare, demo."""
