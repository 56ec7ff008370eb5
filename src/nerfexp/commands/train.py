"""``nerfexp``: build everything from the config, train, test with the last checkpoint; nothing else."""

import contextlib
import difflib
import logging
import math
import os
import re
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.errors import HydraException, InstantiationException, MissingConfigException, OverrideParseException
from hydra.types import RunMode
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import ConfigAttributeError, ConfigKeyError, OmegaConfBaseException

from nerfexp.commands.console import file_error_line, quiet_dependencies, thread_file_errors
from nerfexp.commands.signals import JobSignalled, ending_signals, in_launcher_job, job_signals, received_signal
from nerfexp.data.rays import rank_slice
from nerfexp.errors import ConfigError, NerfexpError, failures_refused
from nerfexp.extras import require
from nerfexp.manifest import record_matching
from nerfexp.reading import UnreadableFile
from nerfexp.rundir.labels import run_labels
from nerfexp.rundir.layout import (
    LAST_CHECKPOINT,
    RESULTS,
    RUN_CONFIG,
    RUN_LIBRARY_FILES,
    is_global_zero,
    planned_jobs,
    read_json,
    write_status,
)
from nerfexp.settings.checks import check_composition, check_settings
from nerfexp.settings.groups import check_group_overrides, derived_choices, is_nerfexp_group
from nerfexp.settings.rows import check_row
from nerfexp.settings.schema import PASSED_ON, matching
from nerfexp.settings.unused import unused_settings, without_unused

if TYPE_CHECKING:
    import lightning as L
    from lightning.pytorch.loggers import Logger

    from nerfexp.machine_share import ThreadChoice
    from nerfexp.training.recorders import RunRecorder
    from nerfexp.training.resume import Resumed

log = logging.getLogger("nerfexp")


def train(cfg: DictConfig) -> dict | None:
    """Train on ``cfg.data``, then score the test split with the last checkpoint; everything is written
    to the run's directory. Returns the run's results (see ``RunRecorder``) in global rank 0, else None.

    The test loads the checkpoint because under ``trainer=ddp`` (Lightning's ``ddp_spawn``) ``fit`` and
    ``test`` each run in new processes, and this one gets back only the weights: the checkpoint carries
    the step, the training time and the last validation, and rank 0 leaves the results in ``results.json``.

    Hydra's callbacks checked a single run's settings and its checkpoint (``SettingsCheck``, ``ResumeCheck``)
    before its directory was made; a sweep's job, which they do not see, is checked here.

    Lightning, and what builds on it, is imported here and in the functions below rather than at the top: importing
    it is most of a command's start-up (8 of 12 s on a 2-core CPU, docs/testing.md), which a bad setting need not
    wait for."""
    import lightning as L

    from nerfexp.data.datamodule import fill_ray_bounds
    from nerfexp.training.precision import fill_precision
    from nerfexp.training.recorders import RunRecorder

    hydra_config = HydraConfig.get()
    runtime, overrides = hydra_config.runtime, list(hydra_config.overrides.task)
    unused = check_job(cfg, hydra_config)
    quiet_dependencies()
    instantiate(cfg.data).fetch()  # a scene by name (data.scene): into the cache where it is not there, before any read
    bounds = fill_ray_bounds(cfg)
    L.seed_everything(cfg.seed, workers=True, verbose=False)
    threads = start_job_threads(cfg.threads, hydra_config)
    fill_precision(cfg)  # with the run's threads: auto may time the run's field (on forked random numbers)
    choices, groups = recorded_choices(cfg, runtime.choices), chosen_groups(runtime.choices)
    recorded, settings = recorded_config(cfg, groups, unused)  # before anything is built
    resumed, resumes = checked_resume(cfg, groups, settings, sweep=hydra_config.mode == RunMode.MULTIRUN)
    logger = build_logger(cfg.get("logger"))
    datamodule = instantiate(cfg.datamodule)
    model = build_model(cfg, resumed)
    recorder = RunRecorder(runtime.output_dir, choices, recorded, overrides, settings, resumes, run_labels(cfg),
                           bounds, test_budgets=cfg.test_budgets)
    trainer = instantiate(cfg.trainer, logger=logger, callbacks=run_callbacks(cfg, recorder, threads))
    rank_slice(datamodule.batch_rays, 0, trainer.world_size)  # a batch that the processes cannot share: an error now
    fit_then_test(trainer, model, datamodule, logger, cfg.resume, recorder.output_dir)
    if not trainer.is_global_zero:
        return None
    return logged_results(recorder.output_dir)


def check_job(cfg: DictConfig, hydra_config: DictConfig) -> list[tuple[str, str]]:
    """The command line's settings that this job does not use (``unused_settings``: each warned of here, recorded as
    null), after a sweep's job's settings are checked as Hydra's callbacks check a single run's (its group values and
    labels first, before the others read them; missing mandatory values next; its row). A check that fails refuses
    the job (``failures_refused``), as it refuses a single run."""
    task = list(hydra_config.overrides.task)
    with failures_refused("the settings check"):
        if hydra_config.mode == RunMode.MULTIRUN:
            check_composition(cfg, hydra_config)
            check_settings(cfg)
            check_row(cfg, hydra_config.runtime.choices, task)
        unused = unused_settings(cfg, task)
    for override, reason in unused:
        log.warning("%s: not used with %s; results.json records it as null", override, reason)
    return unused


def start_job_threads(setting: int | None, hydra_config: DictConfig) -> "ThreadChoice":
    """Torch's threads for this job set (``start_threads``: ``setting``, shared with a multirun launcher's jobs at
    once), and said in one line each, with the warnings of a count capped or a busy machine, before any work."""
    from nerfexp.machine_share import start_threads

    launcher = (OmegaConf.to_container(hydra_config.launcher, resolve=True)
                if hydra_config.mode == RunMode.MULTIRUN else None)
    threads = start_threads(setting, launcher)
    log.info("%s", threads.line)
    for warning in (threads.capped, threads.busy):
        if warning is not None:
            log.warning("%s", warning)
    return threads


def recorded_choices(cfg: DictConfig, choices: DictConfig) -> dict:
    """What results.json records of the run's choices: each config group's option (``chosen_groups``) and the
    run's ``hierarchical`` and ``seed``."""
    return {**chosen_groups(choices), "hierarchical": cfg.hierarchical, "seed": cfg.seed}


def chosen_groups(choices: DictConfig) -> dict[str, str]:
    """The option chosen in each config group a user chooses (``group_choices``: Hydra's own groups and those
    left empty aside), those ``config.yaml`` derives from other choices (``derived_choices``:
    acceleration/by_encoding) aside too: results.json and the checkpoints record what was chosen."""
    from nerfexp.training.resume import group_choices

    derived = derived_choices()
    return {group: option for group, option in group_choices(choices).items() if group not in derived}


def recorded_config(cfg: DictConfig, choices: dict[str, str], unused: list[tuple[str, str]]) -> tuple[dict, dict]:
    """The run's config as results.json records it, the ``unused`` settings null (``without_unused``), and its
    settings as its checkpoints record them (``checkpoint_settings``, with the group ``choices``). Called before
    anything is built: Hydra's instantiate resolves in place the sections a built one names
    (model.renderer.sampler: ${sampler}), and ``without_unused`` follows the references as written."""
    from nerfexp.training.resume import checkpoint_settings

    resolved = OmegaConf.to_container(cfg, resolve=True)
    recorded = without_unused(cfg, resolved, [override for override, _ in unused])
    return recorded, checkpoint_settings(OmegaConf.create(resolved), choices)


def checked_resume(cfg: DictConfig, choices: dict[str, str], settings: dict,
                   sweep: bool) -> "tuple[Resumed | None, list[dict]]":
    """The checkpoint ``cfg.resume`` names, read, and the record of the resumes that led to this run (``settings``:
    this run's, ``checkpoint_settings``): a checkpoint this run may not continue is an error before any work (a
    sweep's job checked here, as ``ResumeCheck`` checked a single run's). ``(None, [])`` where the run starts anew."""
    from nerfexp.training.resume import check_resume, read_resumed, resume_record

    if cfg.resume is None:
        return None, []
    checkpoint = Path(cfg.resume)
    resumed = check_resume(cfg, choices, checkpoint) if sweep else read_resumed(checkpoint)
    return resumed, resume_record(resumed, checkpoint, settings["settings"])


def build_model(cfg: DictConfig, resumed: "Resumed | None") -> "L.LightningModule":
    """The run's model (``cfg.model``), sized as the weights of the checkpoint it resumes (``resumed``) are, where
    the data sizes them, as Lightning will; weights of another network are an error before any work
    (``check_weights``: a checkpoint that records no settings may hold another network size)."""
    from nerfexp.products.trained import check_weights

    model = instantiate(cfg.model)
    if resumed is not None:
        model.on_load_checkpoint({"state_dict": resumed.weights})
        check_weights(resumed.weights, model, Path(cfg.resume))
    return model


def run_callbacks(cfg: DictConfig, recorder: "RunRecorder", threads: "ThreadChoice") -> list:
    """The trainer's callbacks: those of ``cfg.callbacks``, the run's ``recorder`` and its progress bars, and those
    the run's settings ask for: the thread count following the machine's load (an automatic count: the changes are
    results.json's thread_changes), the refined training cameras written into the run (``camera_opt=so3xr3``), and
    SIGTERM left to ``job_signals`` in a launcher's job, not to Lightning (``KeepSigtermHandler``)."""
    from nerfexp.machine_share import available_cpus
    from nerfexp.training.callbacks import KeepSigtermHandler, ThreadsFollowLoad
    from nerfexp.training.pose_records import RefinedPoses
    from nerfexp.training.progress import progress_bars

    callbacks = [instantiate(c) for c in cfg.callbacks.values()] + [recorder] + progress_bars(cfg.trainer)
    if threads.follows_load:
        callbacks.append(ThreadsFollowLoad(available_cpus(), recorder.thread_changes))
    if cfg.model.get("camera_opt") is not None:
        callbacks.append(RefinedPoses(recorder.output_dir))
    if in_launcher_job():
        callbacks.append(KeepSigtermHandler())
    return callbacks


def fit_then_test(trainer: "L.Trainer", model: "L.LightningModule", datamodule: "L.LightningDataModule",
                  logger: "Logger | bool", resume: str | None, run_dir: Path) -> None:
    """Train ``model`` (from the checkpoint ``resume`` where set), then test the checkpoint the training wrote (into
    ``run_dir``);
    checkpoints are read as data (weights_only), whoever wrote them. The logger is finished either way, as
    succeeded only where both ran to the end."""
    from nerfexp.training.loggers import finish

    succeeded = False
    try:
        trainer.fit(model, datamodule=datamodule, ckpt_path=resume, weights_only=True)
        # the checkpoint this run wrote: ModelCheckpoint's own record of it where fit ran in this process
        written = (getattr(trainer.checkpoint_callback, "last_model_path", "")
                   or run_dir / LAST_CHECKPOINT)
        trainer.test(model, datamodule=datamodule, ckpt_path=written, verbose=False, weights_only=True)
        succeeded = True
    finally:
        finish(logger, succeeded)


def logged_results(run_dir: Path) -> dict:
    """The finished run's results (``results.json`` in ``run_dir``), said in one line: its scores, steps, time and
    precision, a warning where every test view rendered nothing (``collapse``)."""
    from nerfexp.training.recorders import scores_text

    results = read_json(run_dir / RESULTS)
    level = logging.WARNING if results["collapse"] else logging.INFO  # scores of a render of nothing: said as such
    log.log(level, "%s after %d steps in %.0f s (%s); outputs in %s", scores_text(results), results["steps"],
            results["train_time_s"], results["precision"], run_dir)
    return results


def build_logger(cfg: DictConfig | None) -> "Logger | bool":
    """The run's Lightning logger (``conf/logger/``), or False for none; a ConfigError where the logger's
    package is not installed."""
    if not cfg:
        return False
    try:
        return instantiate(cfg)
    except InstantiationException as error:
        if not isinstance(error.__cause__, ModuleNotFoundError):
            raise
        raise ConfigError(f"logger._target_={cfg._target_} needs a package that is not installed ({error.__cause__}); "
                          'pip install -e ".[mlflow]" or ".[wandb]" installs those of logger=mlflow and logger=wandb, '
                          "and logger=tensorboard, csv or none need nothing more") from error


@hydra.main(version_base=None, config_path="pkg://nerfexp.conf", config_name="config")
def main(cfg: DictConfig) -> float | None:
    """Run one job; its status goes to ``status.json`` (a finished run's with ``collapse``, as ``results.json``'s:
    null, or the line saying that every test view rendered nothing). Returns what a hyper-parameter sweeper
    (``+sweeps=optuna``) maximizes (``sweep_objective``).

    A single run with bad input ends with one line on stderr and exit status 1. In a multirun the
    error is raised instead, so that Hydra records this job as failed and goes on with the others
    (the sweep then ends with the first job's error; ``nerfexp-report`` lists the failed jobs).

    What Hydra, Lightning's loggers and callbacks write into the run directory is recorded in its manifest
    (``nerfexp.manifest``; ``RUN_LIBRARY_FILES`` and the job's log): Hydra's config as the job starts,
    everything when it ends, finished or failed, so that a failed run's files can be shown to be nerfexp's."""
    hydra_config = HydraConfig.get()
    output_dir, overrides = hydra_config.runtime.output_dir, list(hydra_config.overrides.task)
    writes = is_global_zero()  # under SLURM every process of a distributed job runs this; rank 0 records
    labels = run_labels(cfg)  # in every status: a report shows the tags of a job that did not finish too
    if writes:
        write_status(output_dir, "running", overrides, **labels)
        record_matching(output_dir, (RUN_CONFIG.parent.name,))  # Hydra wrote it before the job started
        if hydra_config.mode == RunMode.MULTIRUN:
            try:
                planned = planned_jobs(Path(hydra_config.runtime.cwd) / hydra_config.sweep.dir)
            except UnreadableFile:  # the sweep's own file, being written by Hydra: the count is a courtesy
                planned = None
            log.info("job %d%s: %s", hydra_config.job.num + 1, f" of {planned}" if planned else "", output_dir)
    try:
        with job_signals():  # a launcher's job (SLURM): SIGTERM handled as cli handles it
            results = train(cfg)
    except BaseException as error:  # an interrupt too: the job did not finish
        # the signal: from nerfexp's handlers (cli, job_signals), else Lightning's SIGTERM handling
        ended_by = received_signal() or ("SIGTERM" if lightning_sigterm(error) else None)
        unrecorded = ""  # where status.json cannot say it (a full disk), the error's line does
        if writes:
            details = {"signal": ended_by, "error": f"ended by {ended_by}"} if ended_by else {
                "error": f"{type(error).__name__}: {error}"}
            try:
                write_status(output_dir, "failed", overrides, **details, **labels)
            except OSError as status_error:
                unrecorded = f"; not recorded in status.json ({file_error_line(status_error)})"
        if ended_by and in_launcher_job():  # an Exception, which the launcher returns to the sweep
            line = signalled_job_line(Path(output_dir), ended_by)
            log.error("job failed: %s", line)
            raise JobSignalled(line) from None
        # bad input, a class the config names, or a file that cannot be written (a full disk, a read-only folder)
        if isinstance(error, NerfexpError | InstantiationException | OSError):
            line = hydra_error_line(error)
            if isinstance(error, OSError) and error.filename is None:  # a library's write (a logger's): no file
                line += f" while training into {output_dir}"
            line += unrecorded
            if hydra_config.mode == RunMode.RUN:
                sys.exit(f"nerfexp: error: {line}")
            log.error("job failed: %s", line)
        raise
    finally:
        if writes:  # a record that cannot be written costs only a refusal to replace these files later
            with contextlib.suppress(OSError):
                record_matching(output_dir, (*RUN_LIBRARY_FILES, f"{hydra_config.job.name}.log"))
    if results is None:  # not global rank 0
        return None
    write_status(output_dir, "finished", overrides, collapse=results["collapse"], **labels)
    return sweep_objective(results)


def sweep_objective(results: dict) -> float:
    """What a hyper-parameter sweeper maximizes of a finished run's ``results``: the last validation PSNR; for a run
    that rendered nothing (``collapse``), -inf, below every run that rendered something, so never the best trial
    (Optuna's TPE takes it as a completed trial; a NaN would make Hydra's Optuna sweeper fail)."""
    return -math.inf if results["collapse"] else results["val_psnr"]


def signalled_job_line(run_dir: Path, signal_name: str) -> str:
    """What a launcher's job ended by ``signal_name`` says: the run and how to continue it."""
    checkpoint = run_dir / LAST_CHECKPOINT
    advice = (f"the job's overrides with resume={checkpoint} continue it" if checkpoint.is_file()
              else "it saved no checkpoint")
    return f"{run_dir}: ended by {signal_name} (on SLURM: a time limit, scancel or preemption); {advice}"


def lightning_sigterm(error: BaseException) -> bool:
    """Whether ``error`` is Lightning's SIGTERMException (SIGTERM to a job under submitit), which only a
    process that imported Lightning can raise: a bad setting's process is not made to import it to say no."""
    exceptions = sys.modules.get("lightning.pytorch.utilities.exceptions")
    return exceptions is not None and isinstance(error, exceptions.SIGTERMException)


# Keys that moved to the component that reads them ({old key: the key now}), named when an old one is set
MOVED_KEYS = {
    "scale.hash_log2_table_size": "encoding.position.log2_table_size",  # conf/encoding/hashgrid_sizes/
    "scale.hash_finest": "encoding.position.finest",
}

# hydra/launcher=slurm (conf/hydra/launcher/slurm.yaml) and the plugin's own submitit_slurm, submitit_local
SUBMITIT_LAUNCHER = re.compile(r"\+*hydra/launcher=(slurm|submitit_\w+)")


def check_launcher(arguments: list[str]) -> None:
    """A MissingExtraError where the command line picks a submitit launcher whose plugin is not installed
    (Hydra would only say that it cannot find the launcher's config)."""
    for argument in arguments:
        if SUBMITIT_LAUNCHER.fullmatch(argument):
            require("hydra_plugins.hydra_submitit_launcher", argument)


def cli() -> None:
    """The ``nerfexp`` command: ``main``, where SIGTERM or SIGINT (a SLURM time limit, ``kill``, Ctrl-C)
    ends a run or a sweep with exit status 128 + the signal, after the job's ``status.json`` says
    which signal ended it (``nerfexp.commands.signals``). Standard output is line-buffered, so that a log
    redirected to a file (a SLURM log) shows each line when it is printed, not when the run ends."""
    sys.stdout.reconfigure(line_buffering=True)
    try:
        check_launcher(sys.argv[1:])
        check_group_overrides(sys.argv[1:], is_nerfexp_group)
    except NerfexpError as error:
        sys.exit(f"nerfexp: error: {error}")
    with ending_signals("nerfexp"), thread_file_errors("nerfexp"), hydra_errors_in_one_line():
        main()


@contextlib.contextmanager
def hydra_errors_in_one_line() -> Iterator[None]:
    """Inside the block, Hydra's and OmegaConf's errors (an unknown option or key, an override's syntax, a
    class that cannot be built), nerfexp's and a file's (an OSError) end the program with one line
    (``hydra_error_line``) and exit status 1. Hydra prints its own multi-line report unless
    HYDRA_FULL_ERROR=1, which makes it re-raise: so it is set inside the block, and a user's own
    HYDRA_FULL_ERROR=1 keeps Hydra's full output."""
    if os.environ.get("HYDRA_FULL_ERROR") == "1":
        yield
        return
    os.environ["HYDRA_FULL_ERROR"] = "1"
    try:
        yield
    except (HydraException, OmegaConfBaseException, NerfexpError, OSError) as error:
        sys.exit(f"nerfexp: error: {hydra_error_line(error)}")
    finally:
        del os.environ["HYDRA_FULL_ERROR"]


def hydra_error_line(error: Exception) -> str:
    """One line for an error of Hydra, OmegaConf or nerfexp: the override at fault and what was expected;
    for an OSError, the file and why (``file_error_line``; Hydra's MissingConfigException is an OSError too)."""
    if isinstance(error, OSError) and not isinstance(error, HydraException):
        return file_error_line(error)
    cause = error.__cause__
    if isinstance(error, MissingConfigException) and error.options is not None:
        group, _, option = str(error.missing_cfg_file).rpartition("/")
        return f"{group}={option}: no such option (choose from {', '.join(error.options)})"
    if isinstance(error, OverrideParseException):
        return f"{error.override}: not a valid override ({error.message.splitlines()[0]}; see Hydra's override grammar)"
    if isinstance(cause, ConfigKeyError | ConfigAttributeError) and "Could not override" in str(error):
        key = cause.full_key
        override = next((a for a in sys.argv[1:] if a.split("=", 1)[0] == key), key)
        parent = cause.parent_node
        known = [str(k) for k in parent.keys() if k != "hydra"] if parent is not None else []
        section, _, leaf = key.rpartition(".")
        close = difflib.get_close_matches(leaf, known, n=1)
        advice = [f"the closest: {section + '.' if section else ''}{close[0]}"] if close else []
        if key in MOVED_KEYS:  # a key an earlier nerfexp had: where its setting is now
            advice = [f"it moved to {MOVED_KEYS[key]}"]
        if matching(PASSED_ON, key):  # a keyword argument nerfexp's config does not set: its class checks it
            advice.append(f"+{override} adds one")
        return (f"{override}: no such key ({section or 'the config'} has {', '.join(known)}"
                f"{'; ' if advice else ''}{'; '.join(advice)})")
    text = " ".join(line.strip() for line in str(error).splitlines() if line.strip())
    if isinstance(error, InstantiationException) and cause is not None:
        text = f"{text} ({type(cause).__name__}: {' '.join(str(cause).split())})"
    return text
