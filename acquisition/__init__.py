"""Capture sessions: drive the rig through drivers/ interfaces and write streak stacks to Zarr."""
