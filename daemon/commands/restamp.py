"""``nanodrift restamp M.json [--out M2.json]``: give a deliberately edited model file its new id.

A model's id is the hash of its content (:meth:`nanodrift.model.model.Model.content_id`) and
``load_model`` refuses a file whose id does not match, so an edit can never be "reloaded" while the
daemon keeps serving the old coefficients under the same id. After a deliberate hand edit this
command checks everything else in the file exactly as a load does, then writes it (atomically) with
the id of what it now holds, recording the previous id in ``provenance.restamped_from``.
"""

from __future__ import annotations

import argparse
import datetime as dt

from nanodrift.errors import UserError, user_errors
from nanodrift.model.cell_model import CellModel, load_any_model, save_cell_model
from nanodrift.model.model import ModelFileError


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", metavar="M.json", help="the edited model file")
    parser.add_argument("--out", metavar="M2.json", help="write here instead of over M.json")


def main(args: argparse.Namespace) -> int:
    with user_errors(ModelFileError):
        model = load_any_model(args.model, check_id=False)
    old, new = model.id, model.content_id()
    # a multi-axis file: every axis' model carries its own id too (the cell's id hashes their contents)
    axes_stale = any(m.id != m.content_id() for m in CellModel.of(model).models.values())
    out = args.out or args.model
    if old == new and not axes_stale and out == args.model:
        print(f"{args.model}: id {new} already matches its content; nothing written")
        return 0
    if old != new or axes_stale:
        model.provenance["restamped_from"] = old or None
        model.provenance["restamped"] = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
    try:
        save_cell_model(CellModel.of(model), out)
    except OSError as err:
        raise UserError(f"{out}: cannot write the model file ({err.strerror or err})") from None
    print(f"{args.model}: id {old or '(none)'} -> {model.id}" + (f", written to {out}" if out != args.model else ""))
    return 0
