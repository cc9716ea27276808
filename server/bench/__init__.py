"""Benchmarks behind ``facecast bench`` (the server's own code); bench/ holds the scripts that write JSON and tables."""
