"""Sensor input: recorded scans, videos, image folders, gradient-map sequences, live cameras."""
