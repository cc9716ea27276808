"""Benchmarks behind ``facecast bench``; bench/ holds the scripts that write JSON and tables."""
