"""Control: matched control points, their ground sigmas, networks and exports."""
