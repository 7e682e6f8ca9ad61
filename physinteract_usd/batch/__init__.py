"""Batch processing's core, knowing nothing of USD or the verbs (`app/batch.py` runs the items):

    manifest.py    the manifest (CSV or JSON): items and their per-item overrides, checked
    keys.py        the inputs' fingerprint and one key per step (what makes a result reusable)
    runner.py      the local process pool (stopping, a worker that dies, progress events)
    ray_runner.py  one Ray task per item (Ray an optional extra: pip install physinteract-usd[ray])
    summary.py     the summary table as CSV and HTML
"""
