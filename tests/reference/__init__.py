"""Independent reference renderers for ``pipeline.simulate`` (issue 14).

* :mod:`.optics`: the thin-lens law and the grid geometry, derived from scratch.
* :mod:`.disk`: exact disk/rectangle intersection areas (pixel-integrated pillboxes).
* :mod:`.smooth`: brute-force time integration of occlusion-free depth-map scenes
  (per-pixel depth, per-time-cell magnification, per-row exposure windows).
* :mod:`.raytrace`: an exact thin-lens ray trace of two planes with a straight edge
  (partial occlusion), and a literal Monte Carlo ray tracer that checks it.
* :mod:`.cases`: the issue's cases, each as (simulator scene + camera, reference render).

Nothing here imports ``pipeline.simulate`` or ``pipeline.psf``; :mod:`.cases` uses the
public ``pipeline`` scene/camera classes only to build the simulator's side.
"""
