"""Datasets: readers (columns, video chunks, transitions, the in-memory expert data), storage (targets, roots,
``meta/iupe.json``, write-beside-then-swap) and the one compatibility check between datasets, envs and checkpoints."""
