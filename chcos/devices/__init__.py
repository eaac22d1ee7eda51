"""devices - layer 3, the device manager of thesis section 6.1.2: the device table (Devtab) with
its last-value buffers, health, limits and safe values; device-map files and their checks; the
reference of every map key; importers from vendor files. The bus drivers are in ``drivers/``.
"""
