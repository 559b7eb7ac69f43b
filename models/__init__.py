"""Shipped sensor model files (TOML), installed as ``polins.models`` package data."""
