"""The radiance models' material for glTF and OBJ (fit/stages/export.py writes it).

Radiance (grid columns 0:3: view-independent exitant radiance in photo units; the view-dependent
radiance exports its radiance seen along the normal, columns 0:3, since neither glTF nor OBJ has a
view-dependent colour, and the view terms stay in the EXR maps; light field mapping its unlit
approximation, fit/models/lfm/export.py): ``radiance * radiance_scale`` clipped to [0, 1], 8-bit sRGB, as
the baseColor of an unlit material (``KHR_materials_unlit``, fallback metallic 0, roughness 0.9 as the
extension suggests); OBJ: map_Kd with ``illum 0``.
"""

from __future__ import annotations

import numpy as np

from texstream.fit.models.registry import ExportMaterial


def radiance_material(grid: np.ndarray, covered: np.ndarray, radiance_scale: float) -> ExportMaterial:
    """The unlit material of a radiance grid (H, W, >= 3): columns 0:3 times ``radiance_scale``, clipped."""
    rad = np.asarray(grid).astype(np.float64)[..., 0:3] * float(radiance_scale)
    clipped = int((rad.max(axis=-1)[covered] > 1.0).sum())
    return ExportMaterial(np.clip(rad, 0.0, 1.0), unlit=True, clipped=clipped, label="radiance", name="radiance")
