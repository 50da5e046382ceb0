"""`sepoa export`, `label-dataset`, `labeller` and `invite`: the commands on the queue database
alone (no server, no trainer), and the database flags every command that opens it shares."""

from __future__ import annotations

import argparse
import os
import sys
import uuid
from typing import TYPE_CHECKING

from sepoa.parser import (
    ID_MAX,
    RUN_ID,
    Command,
    database_url_file_argument,
    fail,
    integer,
    refusing,
)

if TYPE_CHECKING:
    from sqlalchemy.engine import Engine
    from sqlalchemy.orm import Session


def database_args(p: argparse.ArgumentParser, inherit: bool = False) -> None:
    """`inherit`: on a sub-action, where an absent flag keeps the parent parser's value (so
    `sepoa labeller --data-dir D create x` and `sepoa labeller create x --data-dir D` agree).
    The URL's variables are read by `database_url`, in `labelqueue.database_url`'s order."""
    unset = argparse.SUPPRESS if inherit else None
    data = argparse.SUPPRESS if inherit else os.environ.get("SEPOA_DATA_DIR", "data")
    p.add_argument("--database-url", default=unset,
                   help="the queue database (env SEPOA_DATABASE_URL, else the file named by "
                   "SEPOA_DATABASE_URL_FILE; default: sqlite:///<data-dir>/queue.db); a URL "
                   "here shows in `ps`: keep a password in the environment or a "
                   "--database-url-file")
    database_url_file_argument(p, unset)
    p.add_argument("--data-dir", default=data,
                   help="where the SQLite file, runs and clips live (env SEPOA_DATA_DIR)")


LABELLER_ACTIONS = {
    "revoke": "revoke a labeller's access (its labels stay; not the scripted teacher's, "
    "scripted-teacher, whose runs would wait for ever): leasing, answering and taking "
    "answers back stop at once on every server; reads (label count, clips) within "
    "SEPOA_AUTH_CACHE_SECONDS (5 s); an operator-role labeller loses everything at once",
    "activate": "restore a revoked labeller's access",
    "token": "give a labeller (not scripted-teacher) a new token (printed once): the old one "
    "stops leasing, answering and taking answers back at once on every server, and reading within "
    "SEPOA_AUTH_CACHE_SECONDS (5 s) (an operator-role labeller's: everything at once)",
}
NAME_MAX = 100
LABEL_FORMATS = ("jsonl", "csv", "parquet")
DATASET_FORMATS = ("arrow", "hdf5")
"""`rundata.dataset.DATA_FORMATS` (not imported here: it would load the dataset module)"""


def database_url(args: argparse.Namespace) -> str:
    """The queue database's URL: --database-url or --database-url-file, else
    SEPOA_DATABASE_URL, else the file SEPOA_DATABASE_URL_FILE names, else the SQLite file in
    --data-dir; ValueError when it is not one this app can open, or its file cannot be read."""
    from labelqueue import check_url, sqlite_url
    from labelqueue import database_url as given_url

    return check_url(given_url(args.database_url, args.database_url_file)
                     or sqlite_url(args.data_dir))


def existing_queue(args: argparse.Namespace) -> str:
    """`database_url` for a command that needs a queue to be there (it only reads it, or
    changes what is in it), which it never makes: ValueError naming the place where none is,
    and how one is made; or what is there when it is no queue or damaged (`check_database`)."""
    from labelqueue import check_database
    from labelqueue.schema import sqlite_file

    url = database_url(args)
    path = sqlite_file(url)
    if path is not None and not os.path.isfile(path):
        raise ValueError(f"no queue database at {path}: `sepoa up` or `sepoa serve` with the "
                         "same --data-dir or --database-url makes one")
    # A damaged file can read back fewer labels than it holds, without an error.
    check_database(url)
    return url


def _export_arguments(p: argparse.ArgumentParser) -> None:
    database_args(p)
    p.add_argument("--format", choices=(*LABEL_FORMATS, *DATASET_FORMATS), default=None,
                   help="the label file's: jsonl (default), csv or parquet; with --dataset, "
                   "Minari's storage: arrow (default) or hdf5 (which TorchRL reads)")
    p.add_argument("--run", type=RUN_ID, default=None, help="one run's labels only")
    p.add_argument("--out", default="-", help="file to write; - for standard output")
    p.add_argument("--dataset", default=None, metavar="DIR",
                   help="write the run's episodes and labels as a Minari dataset under "
                        "the datasets folder DIR (needs --run; docs/EXPORT.md)")
    p.add_argument("--dataset-id", default=None,
                   help="with --dataset: the Minari dataset id (default "
                        "sepoa/<task>/run-<N>-v0)")
    p.add_argument("--clips-dir", default=None,
                   help="with --dataset: the clips folder, which holds the runs' episodes "
                        "(env SEPOA_CLIPS_DIR; default <data-dir>/clips)")


def _export(args: argparse.Namespace) -> int:
    from sqlalchemy.exc import DBAPIError

    from labelqueue import NotFound, make_engine, mask_url, session_factory
    from labelqueue.errors import database_reason
    from rundata.label_files import write_export

    if args.dataset is None and (args.dataset_id is not None or args.clips_dir is not None):
        return fail("--dataset-id and --clips-dir go with --dataset DIR")
    url = existing_queue(args)
    if args.dataset is not None:
        return _export_dataset(args, url)
    if args.format in DATASET_FORMATS:
        return fail(f"--format {args.format} is a dataset's storage: it goes with --dataset DIR")
    fmt = args.format or "jsonl"
    if args.out != "-":
        folder = os.path.dirname(os.path.abspath(args.out))
        if not os.path.isdir(folder):
            return fail(f"--out {args.out}: the folder {folder} does not exist; give a file in "
                        "an existing folder, or - for standard output")
        if os.path.isdir(args.out):
            return fail(f"--out {args.out} is a folder; give a file name, or - for standard "
                        "output")
    engine = make_engine(url)
    tmp = None
    try:
        with session_factory(engine)() as session:
            if args.out == "-":
                rows = write_export(session, fmt=fmt, out=sys.stdout.buffer, run_id=args.run)
            else:
                # A name of its own beside --out, so two exports to one file never write into
                # one temporary file; made with the umask's mode, as the file itself would be.
                tmp = os.path.join(os.path.dirname(os.path.abspath(args.out)),
                                   f".{os.path.basename(args.out)}.{uuid.uuid4().hex[:12]}"
                                   ".partial")
                with open(tmp, "xb") as f:
                    rows = write_export(session, fmt=fmt, out=f, run_id=args.run)
                os.replace(tmp, args.out)
    except NotFound as err:
        return fail(str(err))
    except DBAPIError as err:
        return fail(f"cannot read labels from {mask_url(url)}: {database_reason(err)}")
    except OSError as err:
        return fail(f"cannot write --out {args.out}: {err.strerror or err}")
    finally:
        engine.dispose()
        if tmp is not None and os.path.exists(tmp):
            os.remove(tmp)
    print(f"{rows} labels exported", file=sys.stderr)
    return 0


def _export_dataset(args: argparse.Namespace, url: str) -> int:
    from pathlib import Path

    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import DBAPIError

    from labelqueue import NotFound, make_engine, session_factory
    from labelqueue.errors import database_reason
    from rundata.dataset import DatasetError, NoEpisodes, write_dataset
    from rundata.episodes import episodes_dir

    if args.run is None:
        return fail("--dataset needs --run N: a dataset holds one run's episodes")
    if args.format in LABEL_FORMATS or args.out != "-":
        return fail(f"--dataset writes a folder; --format {'/'.join(LABEL_FORMATS)} and --out "
                    f"are for the label file (a dataset's --format: {'/'.join(DATASET_FORMATS)})")
    if os.path.exists(args.dataset) and not os.path.isdir(args.dataset):
        return fail(f"--dataset {args.dataset} is a file; give a folder")
    clips_dir = args.clips_dir or os.environ.get("SEPOA_CLIPS_DIR")
    clips = Path(clips_dir) if clips_dir else Path(args.data_dir) / "clips"
    engine = make_engine(url)
    try:
        with session_factory(engine)() as session:
            summary = write_dataset(session, run_id=args.run, clips_root=clips,
                                    root=Path(args.dataset), dataset_id=args.dataset_id,
                                    data_format=args.format or "arrow")
    except NoEpisodes as err:
        if episodes_dir(clips, args.run).is_dir():
            return fail(str(err))
        return fail(f"run {args.run} has no stored episodes in the clips folder {clips} "
                    f"({episodes_dir(clips, args.run)} does not exist): give the clips folder "
                    "its worker wrote to with --clips-dir (a run trained by `sepoa experiment "
                    "run` or the Slurm script: --clips-dir <results>/clips); a run that never "
                    "opened a round, or trained before this version, has none")
    except (NotFound, DatasetError) as err:
        return fail(str(err))
    except DBAPIError as err:
        return fail(f"cannot read labels from "
                    f"{make_url(url).render_as_string(hide_password=True)}: "
                    f"{database_reason(err)}")
    except OSError as err:
        where = f" ({err.filename})" if err.filename else ""
        return fail(f"cannot write --dataset {args.dataset}{where}: {err.strerror or err}")
    finally:
        engine.dispose()
    left = (f"; {summary.labels_left_out} labels left out (their episodes were not kept)"
            if summary.labels_left_out else "")
    print(f"{summary.dataset_id}: {summary.episodes} episodes, {summary.steps} steps, "
          f"{summary.labels} labels on {summary.queries} queries{left} in {summary.path}\n"
          f"load it with MINARI_DATASETS_PATH={args.dataset} and "
          f"minari.load_dataset({summary.dataset_id!r})", file=sys.stderr)
    return 0


def _label_dataset_arguments(p: argparse.ArgumentParser) -> None:
    from rundata.labelling import LABELLING_SELECTIONS

    database_args(p)
    p.add_argument("dataset", metavar="DATASET",
                   help="a dataset export's folder (sepoa export --dataset), or its Minari "
                   "id under MINARI_DATASETS_PATH; workers read it at the same path")
    p.add_argument("--budget", type=integer("a budget", 1, ID_MAX), required=True,
                   help="answers to ask for in all")
    p.add_argument("--per-round", type=integer("a round size", 1, ID_MAX), default=None,
                   help="pairs per round (default: the preset's)")
    p.add_argument("--selection", choices=LABELLING_SELECTIONS, default="disagreement",
                   help="how rounds after the first (uniform) draw their pairs: uniformly, "
                   "or by the disagreement of the reward ensemble refitted on the labels "
                   "so far (default)")
    p.add_argument("--segment-length", type=integer("a segment length", 1, ID_MAX),
                   default=None, help="steps per clip (default: the preset's, at most the "
                   "dataset's shortest episode)")
    p.add_argument("--name", default=None, help="the run's name (default: label <dataset id>)")
    p.add_argument("--preset", default="small",
                   help="the size preset of the reward ensemble and rounds (default small)")
    p.add_argument("--seed", type=integer("a seed", 0, ID_MAX), default=0)
    p.add_argument("--teacher", choices=("human", "scripted"), default="human",
                   help="who answers: people on the label page (default), or the scripted "
                   "teacher from the dataset's true rewards")
    p.add_argument("--clip-size", default=None, help="256x256 (default), 320x240 or 128x128")
    p.add_argument("--instruction", default=None,
                   help="what labellers are told \"better\" means (default: the task's)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a config override, e.g. reward.hidden_dim=64 or "
                   "feedback.labels_per_query=3 (repeatable; VALUE is JSON, else text)")


def _migrated_engine(args: argparse.Namespace, *, make: bool = True) -> Engine:
    """The queue database, checked and migrated (made where there is none, with `make`);
    ValueError naming what is wrong."""
    from sqlalchemy.exc import DBAPIError

    from labelqueue import check_database, make_engine, migrate
    from labelqueue.errors import database_reason

    if make:
        url = database_url(args)
        check_database(url)
    else:
        url = existing_queue(args)
    try:
        migrate(url)
    except DBAPIError as err:
        raise ValueError(f"cannot open the queue database: "
                         f"{database_reason(err)}") from None
    return make_engine(url)


def _overrides(pairs: list[str]) -> dict[str, object]:
    """`--set KEY=VALUE` flags as config overrides; ValueError naming a malformed one."""
    import json

    out: dict[str, object] = {}
    for pair in pairs:
        key, sep, text = pair.partition("=")
        if not sep or not key:
            raise ValueError(f"--set {pair!r}: give KEY=VALUE, e.g. reward.hidden_dim=64")
        try:
            out[key] = json.loads(text)
        except ValueError:
            out[key] = text
    return out


ANSWERED_BY = {"human": "people label it on the label page",
               "scripted": "the scripted teacher answers from the dataset's true rewards"}


def _label_dataset(args: argparse.Namespace) -> int:
    from sqlalchemy.exc import DBAPIError

    from labelqueue import create_run, session_factory
    from labelqueue.errors import database_reason
    from rundata.labelling import labelling_dataset, labelling_run
    from runvocab.names import ConfigError

    overrides = _overrides(args.set)
    try:
        found = labelling_dataset(args.dataset)
    except ConfigError as err:
        return fail(str(err))
    # Off-screen rendering through EGL unless told otherwise, as the trainer's commands do:
    # before MuJoCo is imported.
    os.environ.setdefault("MUJOCO_GL", "egl")
    try:  # the task's own sizes, where the trainer is installed (a worker checks them anyway)
        from trainer.dataset_labelling import dataset_pool
    except ImportError:
        pass
    else:
        try:
            dataset_pool(found, found.task)
        except ValueError as err:
            return fail(str(err))
    try:  # every check before the database is opened: a refusal leaves no queue.db behind
        fields = labelling_run(
            found, budget=args.budget, per_round=args.per_round, selection=args.selection,
            segment_length=args.segment_length, name=args.name, preset=args.preset,
            seed=args.seed, teacher=args.teacher, config=overrides,
            instruction=args.instruction, clip_size=args.clip_size)
    except ConfigError as err:
        return fail(str(err))
    engine = _migrated_engine(args)
    try:
        with session_factory(engine)() as session:
            run = create_run(session, **fields)
    except ConfigError as err:
        return fail(str(err))
    except DBAPIError as err:
        return fail(f"cannot use the queue database: {database_reason(err)}")
    finally:
        engine.dispose()
    h = run.config["feedback.segment_length"]
    print(f"run {run.id} ({run.name!r}) queued: {run.budget} answers on pairs of {h}-step "
          f"segments of {len(found.episodes)} episodes of {run.task} in {run.dataset}, "
          f"{args.selection} after a uniform first round; a worker serves it "
          f"(sepoa worker), {ANSWERED_BY[args.teacher]}")
    return 0


def _labeller(args: argparse.Namespace) -> int:
    from sqlalchemy import select
    from sqlalchemy.exc import DBAPIError

    from labelqueue import (
        Conflict,
        Labeller,
        check_person_name,
        create_labeller,
        find_labeller,
        rotate_token,
        session_factory,
        update_labeller,
    )
    from labelqueue.errors import database_reason
    from runvocab.text import filled

    name: str | None = getattr(args, "name", None)  # every action but list has one
    if name is not None and not 1 <= len(name) <= NAME_MAX:  # as POST /api/labellers
        return fail(f"labeller name {name!r} is not valid: give 1 to {NAME_MAX} characters")
    if args.action == "create":  # stored as POST /api/labellers stores it
        try:
            args.name = filled(args.name, f"labeller name {name!r}")
        except ValueError as err:
            return fail(str(err))
    # Only `create` makes a queue: the others need labellers that are there already.
    engine = _migrated_engine(args, make=args.action == "create")
    try:
        with session_factory(engine)() as session:
            if args.action == "create":
                try:
                    check_person_name(args.name)
                    labeller, token = create_labeller(session, name=args.name, role=args.role)
                except Conflict as err:
                    return fail(str(err))
                print(f"{labeller.role} {labeller.name!r} created; its token (shown once):")
                print(token)
            elif args.action == "list":
                for lab in session.scalars(select(Labeller).order_by(Labeller.id)):
                    state = "active" if lab.active else "revoked"
                    print(f"{lab.id}\t{lab.name}\t{lab.role}\t{state}")
            else:
                found = find_labeller(session, name=args.name)
                if found is None:
                    return fail(f"no labeller named {name!r} (sepoa labeller list shows them)")
                if args.action == "token":
                    try:
                        _, token = rotate_token(session, labeller_id=found.id)
                    except Conflict as err:  # the scripted teacher
                        return fail(str(err))
                    print(f"new token for {name!r} (shown once; the old one no longer works):")
                    print(token)
                else:
                    active = args.action == "activate"
                    try:
                        update_labeller(session, labeller_id=found.id, active=active)
                    except Conflict as err:  # revoking the scripted teacher
                        return fail(str(err))
                    print(f"{name!r} {'activated' if active else 'revoked'}")
    except DBAPIError as err:  # damage the integrity check does not see, a database gone away
        return fail(f"cannot use the queue database: {database_reason(err)}")
    finally:
        engine.dispose()
    return 0


def _labeller_arguments(p: argparse.ArgumentParser) -> None:
    database_args(p)
    labeller_sub = p.add_subparsers(dest="action", required=True)
    create = labeller_sub.add_parser("create", help="a new labeller; prints its token once "
                                     "(any name but scripted-teacher, the workers' own)")
    create.add_argument("name")
    create.add_argument("--role", choices=("labeller", "operator"), default="labeller")
    database_args(create, inherit=True)
    database_args(labeller_sub.add_parser("list", help="list labellers"), inherit=True)
    for action, text in LABELLER_ACTIONS.items():
        one = labeller_sub.add_parser(action, help=text)
        one.add_argument("name")
        database_args(one, inherit=True)


def _invite(args: argparse.Namespace) -> int:
    from sqlalchemy.exc import DBAPIError

    from labelqueue import NotFound, make_engine, session_factory
    from labelqueue.errors import database_reason

    engine = make_engine(existing_queue(args))
    try:
        with session_factory(engine)() as session:
            if args.action == "participants":
                return _participants(session, args.invite_id, as_csv=args.csv)
            return _verify(session, args.code)
    except NotFound as err:
        return fail(str(err))
    except DBAPIError as err:
        return fail(f"cannot read the queue database: {database_reason(err)}")
    finally:
        engine.dispose()


WHY = {"target": "complete: reached the target", "runs_over": "complete: the run ended",
       "paused": "complete: paused by check pairs",
       "nothing_left": "complete: nothing left to label",
       "entry_failed": "let go: failed the entry test, not to be paid", None: "not complete yet",
       "not_complete": "not complete yet"}


def _verify(session: Session, given: list[str]) -> int:
    """One code (its words joined: a code typed with spaces is one code), or with `-`, one a
    line from stdin; exit 1 when any is nobody's, not earned or given again (a participant is
    paid once), 2 when none is given."""
    from crowdstudy.participants import verify_codes

    codes = sys.stdin.read().splitlines() if given == ["-"] else [" ".join(given)]
    if not any(code.strip() for code in codes):
        return fail("no completion code given" + (" on stdin (one a line)" if given == ["-"]
                                                  else ""))
    checked = verify_codes(session, codes)
    for check in checked:
        if check.why == "unknown":
            print(f"{check.code!r} is no participant's completion code (check it was copied "
                  "whole)", file=sys.stderr)
            continue
        if check.repeat:
            print(f"again: {check.participant or '-'} (labeller {check.labeller!r}, id "
                  f"{check.labeller_id}): their code was given above, pay them once")
            continue
        target = "" if check.target_answers is None else f" of {check.target_answers}"
        print(f"{'valid' if check.valid else 'not earned'}: {check.participant or '-'} "
              f"(labeller {check.labeller!r}, id {check.labeller_id}), invite "
              f"{check.invite_id}, run {check.run_id if check.run_id is not None else 'all'}: "
              f"{check.counted}{target} decisive answers; {WHY[check.why]}")
    return 0 if checked and all(check.valid for check in checked) else 1


def _participants(session: Session, invite_id: int, *, as_csv: bool) -> int:
    import csv
    from dataclasses import asdict

    from crowdstudy.participants import CSV_COLUMNS, participants

    people = participants(session, invite_id=invite_id)
    if as_csv:
        writer = csv.writer(sys.stdout)
        writer.writerow(CSV_COLUMNS)
        for person in people:
            row = asdict(person)
            writer.writerow(["" if row[c] is None else row[c] for c in CSV_COLUMNS])
        return 0
    for p in people:
        print(f"{p.participant or p.labeller}: {p.decisive + p.equal} decisive, {p.skips} skips"
              f", gold {p.gold_correct}/{p.gold_answers}, {p.completion_code} "
              f"{'earned' if p.code_valid else 'not earned'} ({WHY[p.why]}"
              f"{'' if p.active else ', deactivated'})")
    print(f"{len(people)} joined, {sum(p.code_valid for p in people)} earned their code")
    return 0


def _invite_arguments(p: argparse.ArgumentParser) -> None:
    database_args(p)
    invite_sub = p.add_subparsers(dest="action", required=True)
    verify = invite_sub.add_parser(
        "verify", help="whose completion code it is and whether it is earned (exit 1: nobody's"
                       ", not earned, or a participant's given again: pay once); `-` checks "
                       "one code a line from stdin")
    verify.add_argument("code", nargs="+")
    database_args(verify, inherit=True)
    listed = invite_sub.add_parser(
        "participants", help="everyone who joined the invite: answers, gold score and code")
    listed.add_argument("invite_id", type=integer("an invite id", 1, ID_MAX), metavar="ID")
    listed.add_argument("--csv", action="store_true", help="as CSV, to pay from")
    database_args(listed, inherit=True)


COMMANDS = {
    "export": Command(_export_arguments, refusing(ValueError)(_export)),
    "label-dataset": Command(_label_dataset_arguments, refusing(ValueError)(_label_dataset)),
    "labeller": Command(_labeller_arguments, refusing(ValueError)(_labeller)),
    "invite": Command(_invite_arguments, refusing(ValueError)(_invite)),
}
