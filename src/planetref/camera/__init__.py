"""Camera models: native line scan, USGS CSM ISDs and RPCs."""
