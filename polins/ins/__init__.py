"""Inertial navigation: the Earth model, strapdown mechanization and static alignment."""
