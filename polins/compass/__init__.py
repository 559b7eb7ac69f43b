"""The polarization compass: raw DoFP mosaic -> Stokes -> E-vectors -> sun vector -> heading."""
