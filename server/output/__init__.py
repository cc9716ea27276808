"""Output formats: animated glTF, NPZ frames, FAP streams and still previews."""
