"""The throughput benchmark's update settings (tests/benchmarks/bench_training_throughput.py): the
modifiers combine, and a misspelt one is refused before anything is measured."""

import pytest

from tests.benchmarks.bench_training_throughput import parse_update


def test_update_settings_combine_modifiers_and_refuse_unknown_ones():
    assert parse_update("fp32") == ("fp32", set())
    assert parse_update("bf16critic+compile+tf32+syncs") == ("bf16critic", {"compile", "tf32", "syncs"})
    for bad in ("fp16", "bf16+cudagraphs", "bf16critic+compile+autotune", "+compile"):
        with pytest.raises(ValueError, match="unknown update setting"):
            parse_update(bad)
