"""Files shipped with dea-bench: protocol files (``protocols/``, with their JSON schema) and rig files (``rigs/``).

In the source tree these are symbolic links to the repository's top-level ``protocols/`` and ``rigs/`` (the one
copy); a built wheel holds the files themselves. Read them through :mod:`bench.resources`.
"""
