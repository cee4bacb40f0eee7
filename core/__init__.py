"""Shared foundations every other package may use: the forward model, durable and staged writes,
and provenance (the software version).  Imports nothing of ours."""
