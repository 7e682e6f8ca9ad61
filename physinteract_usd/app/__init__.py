"""The application layer: one module per verb, each a plain function that takes paths and options
and returns a result. `physinteract_usd.api` re-exports them; the CLI, the Blender add-on's runner
and the benchmarks call them there. (This package's `__init__` imports nothing, so that the CLI can
load one verb without the others.)

    init.py      init            a stage from a capture
    info.py      info            a stage's summary
    extract.py   extract         contacts, supports, T0 and hand masks from the video
    fit.py       fit             the joint fit, a new model version (prepare_fit / run_fit in parts)
    simulate.py  simulate        a new interaction (spec: interaction_spec.py)
    evaluate.py  evaluate        a fit against synthetic ground truth
    export.py    export          a self-contained asset
    synth.py     synth           a synthetic capture
    batch.py     batch           init -> ... -> export over a manifest (pool or Ray: physinteract_usd.batch)
    adapters.py  the stage -> the core's inputs (observations, contacts, effects)

Where new code goes: a new verb is a new module here (its whole story: what it reads, what it
runs, what it writes); what it computes belongs below (sim/, render/, fit/, extract/, synth/ or a
core module), how it is spelled in USD in usd/, how it is typed in cli/.
"""
