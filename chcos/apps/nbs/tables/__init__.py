"""tables - the Appendix-1 H-module state tables as data (H1.toml, H2.toml, H3.toml).

A package only so that the TOML files travel with chcos (package data) and load through
``importlib.resources``; see NOTES.md here for how the OCR text was transcribed.
"""
