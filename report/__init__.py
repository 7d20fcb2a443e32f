"""The evidence report (`neumip report`): neural materials against the real microgeometry, classical
textured materials and their mip-mapped variant, in images: accuracy per view, error against time,
the model's own trade-offs and stability at the edges of its domain."""
