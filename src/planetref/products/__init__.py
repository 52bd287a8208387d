"""Products of an adjusted strip: orthoimages with overviews."""
