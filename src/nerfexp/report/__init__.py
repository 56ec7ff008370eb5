"""``nerfexp-report``: a sweep's variants side by side, their quality against the compute they cost.

Reads every run under the given directories (a run is a folder holding ``status.json`` or
``results.json``, as ``nerfexp`` writes them), groups runs into variants and writes

- ``report.md`` / ``report.csv``: one row per variant: test PSNR and SSIM, and LPIPS where runs scored
  it (mean and sample standard deviation over the runs of the variant, usually its seeds; LPIPS is
  AlexNet's, never compared with a paper's VGG LPIPS), the difference to a reference variant
  paired by seed with its 95% interval and verdict (``nerfexp.report.comparison``), training time, time per
  step, rays/s, parameters, network evaluations per ray. report.md reads as a result: the table with its verdicts
  first, what its numbers need said below it, each once (``nerfexp.report.tables.table_notes``: the caveats on its
  times among them, ``nerfexp.report.shared_machines``); then the published figures beside a variant only where
  its scenes are the publication's, each with its protocol (``nerfexp.report.publication_tables``); the ranking in
  groups the seeds cannot tell apart, and which pairs of ablation rows agree with the paper's order, are reversed,
  or are not resolved (at the end of training, the step named); then "Per budget": each variant against the
  reference at each step their runs were all tested at and at matched training times
  (``nerfexp.report.budgets``), the verdict column saying where the verdict depends on the budget or is still
  moving; then "At equal training time": the variants ranked at the fastest variant's budgets' times; then every
  job that did not finish (failed, or running / killed) with its reason, every finished run without a test
  score (collapsed, with its message; not scored: a score missing, null, NaN or infinite), and every run whose
  files cannot be read as nerfexp writes them, or whose results.json contradicts itself (damaged: the file, the
  key and why, ``nerfexp.rundir.records``), none of whose numbers is used; last, how the numbers were computed;
- ``report_budgets.csv``: the per-budget differences, one per line (variant, reference, metric, step or time,
  budget, seed pairs, difference, 95% interval, verdict); times compared only between runs on one machine that
  had it to themselves (``nerfexp.report.shared_machines``);
- ``psnr_vs_time.png``: validation PSNR against training wall-clock seconds: each variant's mean over
  seeds with a band from the lowest to the highest seed, single runs faint;
- ``pareto.png``: final test PSNR against total training time (bars: one standard deviation over
  seeds), the Pareto front drawn through the means, each variant's test budgets as small points on a thin line;
- ``difference_vs_time.png``: each variant's test PSNR difference to the reference against training time at
  the matched times, its 95% interval a band;
- ``report.html``: all of the above as a page that opens from disk (``nerfexp.report.page``), and a few
  test views (``--views``) rendered by each variant beside the ground truth, with the render's error
  image and its PSNR and SSIM (and LPIPS); its pictures in ``report_images/``, decoded from the runs' ``test/``
  PNGs and written anew.

The reference is the paper's complete model (``ablation=complete``) where the sweep has it, else the
variant named by ``--reference``; without either the report has no differences.

A variant is the set of a run's command-line overrides without the keys averaged over (``--over``,
default ``seed``; ``--over seed data.scene``: each variant over the scenes of a sweep over them, as the paper's
ablation table is) and the run's tags and notes (``nerfexp.rundir.labels``), leaving out overrides every run
shares. report.md, report.csv and report.html show each variant's tags (those of all its runs) and notes.

The report is written whole or not at all, and says each step of its work as it begins
(``nerfexp.report.folder.write_report``).
"""
