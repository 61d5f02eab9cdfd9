"""Printing the object: textured meshes, flat print sheets with tag cards, and the pre-print check."""
