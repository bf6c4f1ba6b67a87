"""The network: its feature contract, its weight files, and how it is trained.

Read by rendering (NumPy only, no device code here):

- ``layout``      the feature contract between the gather (cl/gather.cl) and the network;
- ``templates``   the template point tables the gather reads (clvol/data/templates.npz);
- ``phasetable``  volume-phase tables and the per-frame phase-feature table;
- ``export``      weight files: ``Architecture``, save, load, contract and domain checks.

Training only (``model`` and ``train`` import torch; nothing on the render path imports them):

- ``dataset``     labelled data sets: shards of gathered features and path-traced labels;
- ``distributed`` the same shards as Ray tasks, on all cores or a cluster;
- ``model``       the network in torch;
- ``train``       samples, loss, the checkpointed trainer.

The render-time source that runs the network (gather + cl/mlp.cl) is clvol/render/ms/network.py.
"""
