"""Benchmarks run by ``streaklab bench NAME``; one module per benchmark."""
