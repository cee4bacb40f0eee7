"""Streak stacks to calibrated (y, x, t) cubes, and cube import/export."""
