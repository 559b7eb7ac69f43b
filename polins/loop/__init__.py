"""The navigation loop: images measured with the INS attitude as prior, streaming and offline."""
