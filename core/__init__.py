"""Shared foundations every other package may use: the forward model, durable and staged writes,
provenance (the software version) and the data layer's error base class.  Imports nothing of ours."""
