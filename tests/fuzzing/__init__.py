"""Fuzzing harnesses (a testing tool, not part of the product: nothing under bench/ imports them).

``files``: mutated protocol and rig files through ``bench validate``'s path; ``wire``: random frames to each twin
and random replies to each driver. tests/test_fuzz.py runs short seeded rounds; the long runs are
``python -m tests.fuzzing.files`` and ``python -m tests.fuzzing.wire`` from the repository root.
"""
