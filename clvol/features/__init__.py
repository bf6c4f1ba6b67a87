"""The feature contract between the gather (cl/gather.cl) and the network (cl/mlp.cl): what the
kernels produce and read, and the weight file. NumPy and SciPy only: no torch, no pyopencl, and
of clvol only the base layer (errors, atomic files); clvol/kernels/ and everything above read it.

- ``layout``      feature and config order, units, levels, versions;
- ``templates``   the template point tables the gather reads (clvol/data/templates.npz);
- ``phasetable``  volume-phase tables and the per-frame phase-feature table;
- ``weights``     the weight file: ``Architecture``, save, load, contract and domain checks.

The device code that runs the network is clvol/kernels/gather.py, gather_mlp.py and mlp.py; the
render-time source is clvol/render/ms/network.py; training is clvol/training/.
"""
