"""The jobs users run: the main job over a focal stack (``stack``), sweep captures
(``sweep``), flexible DOFs from a stack (``dof``) and batches of stacks (``batch``).
Each is built from the cores (:mod:`pipeline.core`), files (:mod:`pipeline.io`) and
dask graphs (:mod:`pipeline.parallel`); the CLI only parses and calls one of them.
"""
