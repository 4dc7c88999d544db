"""Synthetic capture sets with ground truth (:mod:`~texstream.capture.synthetic.synth`, the built-in scenes in
``scenes/``, procedural meshes in :mod:`~texstream.capture.synthetic.procedural`).

A layer above geometry: making a scene's mesh and texture needs mesh IO, cleanup, the atlas and the texel
bake, so nothing else in capture/, calib/ or geometry/ imports this package.
"""
