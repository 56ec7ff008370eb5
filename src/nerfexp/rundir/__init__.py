"""The run directory: the one place that knows the names of the files a run leaves, and how a run is
found and read back.

A run's directory holds (every file written atomically):

- ``status.json``: ``running`` (with host, process id and the process's start), ``finished`` (with
  ``collapse``, as ``results.json``'s) or ``failed`` (with the error), and the run's command-line overrides and
  labels (``tags``, ``notes``: ``nerfexp.rundir.labels``), so a report can list jobs that crashed or still run.
  A status that says ``running`` for a process of this host that is gone is read as a killed run by every reader
  (``nerfexp.rundir.state``).
- ``metrics.jsonl``: one JSON object per evaluation: step, wall_time_s, split, psnr, ssim (means), and
  lpips where LPIPS was scored (``nerfexp.scoring.perceptual``; absent, never NaN, where it was not;
  lpips_custom instead with the user's own weights).
- ``results.json``: final test means and per-view scores (``test_lpips`` too where scored, with
  ``lpips_weights_sha256``, the weights file's SHA-256; ``test_lpips_custom`` for the user's own), last
  validation PSNR, training time, throughput, parameters, the machine, the resolved choices and
  overrides, the tags and notes, and ``collapse``: null, or the line saying that every test view rendered
  nothing (``nerfexp.training.recorders.RunRecorder``, ``nerfexp.scoring.collapse``).
- ``test/``: each test view's render (``r_{i}.png``), ground truth (``r_{i}_target.png``), absolute
  error (``r_{i}_error.png``) and depth (``r_{i}_depth.png``).
- ``checkpoints/last.ckpt``, ``.hydra/config.yaml`` (the composed config, as Hydra saves it).
- ``eval.json`` (``nerfexp-eval``), ``render/`` (``nerfexp-render``), ``export/`` (``nerfexp-export``),
  ``view/camera_path.json`` (``nerfexp-view``'s saved camera path), ``debug/`` (the training guards).

A directory belongs to one run, and a run writes over nothing a user made: ``RunDirectoryGuard`` starts
a run only in a new or empty directory, the run that ``resume`` continues, or that of a run that ended
unfinished without saving a checkpoint (replaced), and a sweep only in a new or empty directory; it
refuses before Hydra writes into the directory. ``nerfexp-manifest.json`` records every file nerfexp wrote
there, with its size and SHA-256, as it is written (``nerfexp.manifest``): a file is replaced or removed only
where it is one of them, unchanged.

A finished (or interrupted) run's files are read back as data by ``find_run``, ``run_config`` and
``read_checkpoint`` (``nerfexp.rundir.trained``); its model is built from them above the training layer
(``nerfexp.products.trained``).
"""
