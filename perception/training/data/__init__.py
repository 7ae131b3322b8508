"""Rendering, writing and reading the datasets (BOP layout), and the pose nets' crops."""
