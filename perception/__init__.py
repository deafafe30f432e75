"""Perception: camera sources, detector, tracker, bounding box -> line of sight."""
