"""``touchreal export nwb SRC --out FILE.nwb``: a ``touchreal record`` MCAP file or a ``touchreal encode``
folder as an NWB file (:mod:`touchreal_client.export.nwb`; docs/ecosystem.md, "Files")."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..params import EncoderParams, default_params
from ..recording import Dataset
from ..server.params_store import params_sha256


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="export a recording to another format (nwb)")
    fmt = p.add_subparsers(dest="format", required=True, metavar="FORMAT")
    n = fmt.add_parser("nwb", help="an MCAP recording or an encode folder -> NWB (units, channels, parameters)")
    n.add_argument("src", type=Path, help="a .mcap file of touchreal record, or a folder of touchreal encode")
    n.add_argument("--out", type=Path, required=True, help="the .nwb file to write")
    n.add_argument("--params", type=Path, default=None,
                   help="encode folder: the parameter file it was encoded with (default: the shipped set, as encode)")
    n.add_argument("--dataset", type=Path, default=None,
                   help="encode folder: its dataset, for the trials' order and durations (default: file order, "
                   "each trial up to the second after its last spike)")
    n.add_argument("--description", default=None, help="the NWB session description")
    n.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    try:
        from touchreal_client.export.nwb import to_nwb
        from touchreal_client.session import read_encode_dir, read_mcap
    except ModuleNotFoundError as exc:
        raise ValueError(f"needs the nwb extra: pip install 'touchreal-client[nwb]' ({exc})") from exc

    if args.src.is_dir():
        params = EncoderParams.load(args.params) if args.params else default_params()
        info = {"rev": 0, "sha256": params_sha256(params), "params": params.model_dump(by_alias=True, mode="json"),
                "source": str(args.params) if args.params else "the shipped parameter set"}
        session = read_encode_dir(args.src, _durations(args.dataset) if args.dataset else None, info)
    elif args.src.is_file():
        if args.params or args.dataset:
            raise ValueError("--params and --dataset are for encode folders (a recording carries its own)")
        session = read_mcap(args.src)
    else:
        raise ValueError(f"{args.src}: no such file or folder")
    out = to_nwb(session, args.out, args.description)
    print(f"{out}: {session.t_us.size} spikes, {len(session.trials)} trials, "
          f"channels {'yes' if session.channels is not None else 'no'}, decoders {sorted(session.decoded) or 'none'}")
    return 0


def _durations(dataset: Path) -> dict[str, float]:
    """Trial id -> duration (s) of its recording, in the dataset's order."""
    ds = Dataset.open(dataset)
    return {str(e["id"]): ds.load(e).duration_s for e in ds.entries()}
