"""A dataset's identity (which data an output folder holds), imported bundles, ``skidbench datasets``."""
