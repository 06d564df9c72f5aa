"""Dataset generation: presets and shards (plan), one shard's work (worker), engines and resume (run)."""

from pressurepose.generate.plan import PRESETS, GenerateConfig, plan_groups, plan_shards

__all__ = ["PRESETS", "GenerateConfig", "plan_groups", "plan_shards"]
