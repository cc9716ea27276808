"""facecast.protocol: wire and file formats as pure encode/decode functions (no I/O, no server imports)."""
