"""Camera-laser extrinsic calibration from checkerboard views (paper section III-E, after Zhang and Pless)."""
