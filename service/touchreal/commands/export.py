"""``touchreal export nwb SRC --out FILE.nwb`` and ``touchreal export rosbag2 SRC OUT``: a ``touchreal
record`` MCAP file or a ``touchreal encode`` folder as an NWB file (:mod:`touchreal_client.export.nwb`)
or a rosbag2 folder for ``ros2 bag play`` (:mod:`touchreal_client.ros2.rosbag2`); docs/ecosystem.md."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from ..params import EncoderParams, default_params
from ..recording import Dataset
from ..server.params_store import params_sha256

if TYPE_CHECKING:
    from touchreal_client.session import Session


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="export a recording to another format (nwb, rosbag2)")
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
    r = fmt.add_parser("rosbag2", help="an MCAP recording or an encode folder -> a rosbag2 folder for ros2 bag play")
    r.add_argument("src", type=Path, help="a .mcap file of touchreal record, or a folder of touchreal encode")
    r.add_argument("out", type=Path, help="the bag folder to create (it must not exist)")
    r.add_argument("--dataset", type=Path, default=None,
                   help="encode folder: its dataset, for the trials' order and durations (default: file order, "
                   "each trial up to the second after its last spike)")
    r.set_defaults(func=run_rosbag2)


def run(args: argparse.Namespace) -> int:
    try:
        from touchreal_client.export.nwb import to_nwb
    except ModuleNotFoundError as exc:
        raise ValueError(f"needs the nwb extra: pip install 'touchreal-client[nwb]' ({exc})") from exc

    session = _session(args.src, args.dataset, args.params)
    out = to_nwb(session, args.out, args.description)
    print(f"{out}: {session.t_us.size} spikes, {len(session.trials)} trials, "
          f"channels {'yes' if session.channels is not None else 'no'}, decoders {sorted(session.decoded) or 'none'}")
    return 0


def run_rosbag2(args: argparse.Namespace) -> int:
    try:
        from touchreal_client.ros2.rosbag2 import write_rosbag2
    except ModuleNotFoundError as exc:
        raise ValueError(f"needs the ros2 extra: pip install 'touchreal-client[ros2]' ({exc})") from exc

    if args.out.exists():  # before reading what may be a long recording
        raise FileExistsError(f"{args.out} exists already (a bag is written as a new folder)")
    session = _session(args.src, args.dataset)
    counts = write_rosbag2(session, args.out)
    stamps = "the recorded clock model" if session.clock else "the recording's start (no clock points)"
    print(f"{args.out}: {sum(counts.values())} messages on {len(counts)} topics ({session.t_us.size} spikes), "
          f"stamped by {stamps}; ros2 bag info {args.out}")
    return 0


def _session(src: Path, dataset: Path | None, params: Path | None = None) -> Session:
    """The recording ``src`` (an MCAP file) or encode folder (with its ``dataset`` and ``params`` file, if
    given; the shipped parameter set otherwise, as encode)."""
    from touchreal_client.session import read_encode_dir, read_mcap

    if src.is_dir():
        p = EncoderParams.load(params) if params else default_params()
        info = {"rev": 0, "sha256": params_sha256(p), "params": p.model_dump(by_alias=True, mode="json"),
                "source": str(params) if params else "the shipped parameter set"}
        return read_encode_dir(src, _durations(dataset) if dataset else None, info)
    if src.is_file():
        given = [f"--{name}" for name, v in (("params", params), ("dataset", dataset)) if v]
        if given:
            raise ValueError(f"{' and '.join(given)}: for encode folders only (a recording carries its own)")
        return read_mcap(src)
    raise ValueError(f"{src}: no such file or folder")


def _durations(dataset: Path) -> dict[str, float]:
    """Trial id -> duration (s) of its recording, in the dataset's order."""
    ds = Dataset.open(dataset)
    return {str(e["id"]): ds.load(e).duration_s for e in ds.entries()}
