"""An independent reference simulator for test data (issue 34, item 1).

An elasto-viscoplastic Herschel-Bulkley MLS-MPM (Yue et al. 2015; shared/reference/model.md) in plain
numpy with numba-compiled kernels (`pip install -e .[reference]`; without numba the same kernels run
as plain Python, slowly). It shares no transfer, contact, return-map or rendering code with jaxfoam:
jaxfoam's reader is used only to check the files written, and its analytic flow curve only in validation.

Modules: material (stress, return map), mpm (transfers, grid boundaries, time loop), scene (scene JSON,
plates, sampling), silhouettes (rendering, HDF5 writer), generate (the data set), validate (analytic checks).

    python -m experiments.reference generate [--case hanging_plate_2d] [--set 0]
    python -m experiments.reference validate
"""
