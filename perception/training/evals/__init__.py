"""Measuring nets on held-out images: pose errors, COCO AP, whole estimators, the paper's
tables."""
