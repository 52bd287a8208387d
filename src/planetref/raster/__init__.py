"""Raster data: DEMs and images on map grids."""
