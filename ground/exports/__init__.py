"""Standard exports of a survey (`pilescan-ground report --export ...`): the points as LAS 1.4, the surface as
a GeoTIFF and a closed mesh, its contours as GeoJSON. docs/exports.md says what each file holds and what opens it.

The package imports no optional library at import time: each writer imports its own (laspy, rasterio, trimesh,
contourpy) when called, so a report without exports needs none of them.
"""
