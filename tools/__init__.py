"""The `slam` command line: thin wrappers over typed library functions."""
