"""Beyond one machine, on ``dask.distributed`` (the ``dask`` extra): sweeps of datasets x presets
as tasks of a cluster, and maps sharded across workers whose queries fan out and merge.

Dask is imported when a cluster is used, never when this package is.
"""

from .cluster import ClusterError, open_client, worker_addresses
from .shards import Shard, ShardedMap, ShardLayout, ShardServer, layout_of_maps, split_map
from .sweep import (
    COLUMNS,
    VOLATILE_COLUMNS,
    SweepDataset,
    SweepOptions,
    SweepResult,
    SweepTask,
    plan_sweep,
    read_table,
    run_sweep,
    run_task,
)

__all__ = [
    "COLUMNS",
    "VOLATILE_COLUMNS",
    "ClusterError",
    "Shard",
    "ShardLayout",
    "ShardServer",
    "ShardedMap",
    "SweepDataset",
    "SweepOptions",
    "SweepResult",
    "SweepTask",
    "open_client",
    "plan_sweep",
    "read_table",
    "run_sweep",
    "run_task",
    "layout_of_maps",
    "split_map",
    "worker_addresses",
]
