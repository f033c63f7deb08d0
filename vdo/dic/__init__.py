"""Correlation on rendered images: the correlation itself (subset and global), the validation of the
predicted uncertainty against it, and the rendered load-path series."""
