"""Benchmarks run by ``balustrade bench``: every ``bench_*.py`` module here defines
``run(quick: bool) -> list[dict]``; each row has at least ``name``, ``median_s`` and,
where a naive baseline is measured in the same run, ``baseline`` and ``ratio``."""
