"""Built-in data: the synthetic polyhedron scene and the published fusion experiments."""
