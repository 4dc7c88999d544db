"""Synthetic capture sets with ground truth (:mod:`~texstream.capture.synthetic.synth`, the built-in scenes in
``scenes/``, procedural meshes in :mod:`~texstream.capture.synthetic.procedural`, the scene's texel materials
in :mod:`~texstream.capture.synthetic.materials`, parameter maps as EXR in
:mod:`~texstream.capture.synthetic.param_maps`, a capture's bare photos in
:mod:`~texstream.capture.synthetic.photos_only`).

A layer above geometry: making a scene's mesh and texture needs mesh IO, cleanup, the atlas and the texel
bake, so nothing else in capture/, calib/ or geometry/ imports this package.
"""
