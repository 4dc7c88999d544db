"""The low layer every stage that draws or sees a mesh shares: the camera struct and its host side
(:mod:`~texstream.render.camera`) and poses aimed at a point (:mod:`~texstream.render.pose`), the shading functions (:mod:`~texstream.render.shading`), depth and
shadow maps (:mod:`~texstream.render.visibility`), the ray-traced renderer (:mod:`~texstream.render.kernels`,
:mod:`~texstream.render.renderer`) and the in-memory mesh (:mod:`~texstream.render.mesh`).

Imports only numpy, warp and texstream.core, so that capture, geometry and fit can all build on it.
"""
