"""The live run: front-end, mapper and navigator threads on a camera and a motor board."""
