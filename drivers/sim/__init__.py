"""Simulated devices that speak the real wire protocols over the real transports."""
