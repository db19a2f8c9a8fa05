"""Learning an explicit approximate PCBF (thesis Chapter 7).

* :mod:`~balustrade.learn.sampler` — Algorithm 7.6 (geometric sampler with warm starts) and
  plain gridding with rejection (Section 7.5);
* :mod:`~balustrade.learn.executors` — local processes (default) or a Dask cluster;
* :mod:`~balustrade.learn.dataset` — resumable sharded Parquet datasets with a manifest;
* :mod:`~balustrade.learn.train` — PyTorch softplus MLP (optional dependency);
* :mod:`~balustrade.learn.export` — the trained network as a CasADi expression/Function;
* :mod:`~balustrade.learn.cli` — ``balustrade sample`` / ``balustrade train``.

Nothing here imports PyTorch at import time.
"""
