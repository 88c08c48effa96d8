"""The checkout's benchmarks and tools: each module here is a program, run as a module of this package.

From the repository root, with the venv's python:

    .venv/bin/python -m scripts.bench_sky --help
    .venv/bin/python -m scripts.make_base_stage            # regenerate stages/

`-m` puts the root first on sys.path, so the modules import this checkout's allo_usd and each other
(`from scripts import benchinfo`, `from scripts.bench_author import scaled_plan`) with no sys.path
edits. Each scripts.bench_* module writes a docs/benchmarks/bench_*.md under scripts.benchinfo's header, which
records the command that made it (`python -m scripts.NAME ARGS`).
"""
