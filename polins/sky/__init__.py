"""The sky: where the sun is (ephemeris) and the polarization pattern it makes (scattering models)."""
