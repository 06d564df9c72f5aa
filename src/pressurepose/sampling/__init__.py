"""Initial pose sampling (seed A.1): partitions, shapes, stratified rejection sampling."""

from pressurepose.sampling.partitions import PARTITIONS, Partition, SamplingConfig, get_partition
from pressurepose.sampling.sampler import InitialPoses, PoseSampler, UnreachableConstraints

__all__ = [
    "PARTITIONS",
    "InitialPoses",
    "Partition",
    "PoseSampler",
    "SamplingConfig",
    "UnreachableConstraints",
    "get_partition",
]
