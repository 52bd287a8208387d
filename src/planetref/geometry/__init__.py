"""Geometry core: each piece of sensor maths written once.

Geodesy, rotations, Lagrange interpolation, bracketed root finding and ray/terrain
intersection live here; cameras, rasters, the simulator and the adjustment import them.
"""
