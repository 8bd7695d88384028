"""The pipelines of ``megalut run`` (reference: ``docs/pipeline.md``, ``docs/great3.md``).

Modules: :mod:`.steps` (the step engine: steps, work units, the work folder and its
manifest), :mod:`.config` (declarations of a pipeline file's keys, the training and
evaluation specs and their readers, shared by both pipelines), :mod:`.file` (the standard
pipeline file: reading, ``extends``, defaults, validation), :mod:`.run` (its steps over the
engine), :mod:`.great3_file` (a GREAT3 branch pipeline file) and :mod:`.great3_run` (its
subfields and branch steps over the engine). The GREAT3 layout, branch simulations and
evaluation are in :mod:`megalut_cli.great3`.
"""
