"""The lab batch: a project file in, every stage run for every session, a report out.

- `project`: the project YAML (sessions, dive logs, calibration, targets, options), loaded
  with errors that name the file and the key.
- `runner`: the stage graph (import, slam, depth per session; merge, sfm, dense for the
  project), content-hash skipping, atomic stage outputs, a log per stage, progress.
- `dask_backend`: where the tasks run (in this process, a local process pool, a Dask
  distributed scheduler, or a SLURM cluster through dask-jobqueue).
- `report`: the self-contained `report.html`.
- `evaluate`: errors against the survey simulator's truth when it is known.

`wreckmap-post run PROJECT.yaml` is the command; `deploy/project.example.yaml` documents
every key of the project file.
"""
