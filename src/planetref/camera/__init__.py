"""Camera models and geodesy: native line scan, USGS CSM ISDs and RPCs."""
