"""Training the network: data sets, labels, the torch model and its training (the top layer
below the applications: it uses the kernels and the path tracer of clvol/render/).

- ``dataset``     labelled data sets: shards of gathered features and path-traced labels;
- ``distributed`` the same shards as Ray tasks, on all cores or a cluster;
- ``labels``      labels at any albedo from per-scattering-order sums traced at albedo 1;
- ``model``       the network in torch;
- ``train``       samples, loss, the checkpointed trainer;
- ``raytrain``    the same training as data-parallel Ray Train workers.

torch is imported by ``model``, ``train`` and ``raytrain`` only; nothing on the render path
imports this package. The feature contract and the weight file it writes are clvol/features/.
"""
