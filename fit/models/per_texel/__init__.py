"""What the per-texel model kinds (Lafortune, diffuse, radiance, view-dependent radiance) share: one
parameter vector per atlas texel (render/layout.py ModelLayout), one streaming fit, one model folder
format (a parameter map per group of columns). Not a plugin itself: the kinds' folders build on it."""
