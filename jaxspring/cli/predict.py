"""`jaxspring predict`: simulate recordings with a fit's values and report the error."""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

from .common import check_writable, same_file


def add_parser(sub):
    parser = sub.add_parser("predict", help="predict recordings with fitted values; print and write the error")
    parser.add_argument("fit", help="fit file written by `jaxspring fit` on recordings")
    parser.add_argument("recordings", nargs="+", help="recording files (.h5 or .csv) to predict")
    parser.add_argument(
        "--out-dir", required=True, help="folder for DIR/<recording stem>.h5 and .png, and DIR/errors.png"
    )
    parser.add_argument(
        "--bands",
        type=int,
        default=0,
        metavar="N",
        help="add a 95%% band from N parameter sets drawn from the fit's covariance (e.g. 64)",
    )
    parser.add_argument("--no-plot", action="store_true", help="skip the figures")
    parser.add_argument("--quiet", action="store_true", help="print only the mean errors")


WRITER = "jaxspring predict"
"""The `writer` attribute of the files `predict` writes (HDF5 attribute, PNG text chunk): the only
existing files it replaces."""


def command(args):
    import tomllib

    import jax

    from ..errors import InputError
    from ..fit.predict import MIN_BAND_DRAWS, BandWarning, predict, summarise
    from ..io.fit_file import load_fitted
    from ..io.recording import load_recording, save_recording
    from ..io.scene import scene_from_dict
    from ..render import plot_error_summary, plot_prediction
    from .fit import print_errors

    jax.config.update("jax_enable_x64", True)
    if args.bands < 0 or 0 < args.bands < MIN_BAND_DRAWS:
        raise InputError(
            "--bands",
            f"{args.bands} parameter set(s) cannot make a 95% band",
            f"give 0 (no band) or at least {MIN_BAND_DRAWS}, such as 64",
        )
    out_dir = Path(args.out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError("--out-dir", f"{str(out_dir)!r} is a file", "give a folder")
    if out_dir.is_symlink() and not out_dir.exists():
        raise InputError("--out-dir", f"{str(out_dir)!r} is a link to nothing", "give a folder, or remove the link")
    stems = [Path(p).stem for p in args.recordings]
    if len(set(stems)) != len(stems):
        raise InputError("recordings", "two recordings share a file name", "give recordings with distinct names")
    if "errors" in stems and not args.no_plot:
        raise InputError("recordings", "a recording named errors would overwrite errors.png", "rename it")
    fitted = load_fitted(args.fit)
    info = fitted["prediction"]
    scene = scene_from_dict(tomllib.loads(info["scene_toml"]))
    recordings = [load_recording(p) for p in args.recordings]
    outputs = [out_dir / f"{stem}.h5" for stem in stems]
    pictures = [] if args.no_plot else [path.with_suffix(".png") for path in outputs] + [out_dir / "errors.png"]
    for path in outputs + pictures:  # every refusal before anything is made or written
        if any(same_file(path, Path(source)) for source in [args.fit, *args.recordings]):
            raise InputError("--out-dir", f"{str(path)!r} is also an input of this command", "choose another folder")
        if path.is_dir():
            raise InputError("--out-dir", f"{str(path)!r} is a folder", "choose another --out-dir")
        if path.exists() and not written_here(path):
            raise InputError(
                "--out-dir",
                f"{str(path)!r} exists and was not written by `jaxspring predict`",
                "choose a new or empty --out-dir (predict never replaces other files)",
            )
    check_writable(_existing_ancestor(out_dir), "--out-dir")
    if args.bands and fitted["covariance"] is None:
        raise InputError(
            "--bands", f"{args.fit} has no parameter covariance", "fit again with the identifiability report"
        )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", BandWarning)
        predictions = predict(
            scene,
            fitted["final"],
            recordings,
            info["markers"],
            info["driven"],
            info["start"],
            info.get("smooth", 0),
            names=tuple(stems),
            covariance=fitted["covariance"],
            noise_std=fitted["noise_std"],
            samples=args.bands,
            marker_names=info.get("marker_names"),
        )
    for warning in caught:
        if issubclass(warning.category, BandWarning):
            print(f"jaxspring: warning: {warning.message}", file=sys.stderr)
    out_dir.mkdir(parents=True, exist_ok=True)
    for path, rec, p in zip(outputs, recordings, predictions):
        save_recording(
            path,
            type(rec)(t=rec.t, x=p.x, markers=p.marker_names),
            bands=(p.low, p.high) if args.bands else None,
            writer=WRITER,
        )
        if not args.no_plot:
            plot_prediction(p, path.with_suffix(".png"), writer=WRITER)
    summary = summarise(predictions)
    if args.quiet:
        print(
            f"mean |error| per coordinate {1e3 * summary.mean_coordinate_error:.3f} mm, "
            f"mean distance {1e3 * summary.mean_distance:.3f} mm"
        )
    else:
        print_errors("recording", predictions)
    if args.bands:
        unstable = predictions[0].band_unstable
        drawn = f"{args.bands - unstable} of {args.bands} parameter sets"
        drawn += f"; {unstable} blew up and were left out" if unstable else ""
        print(f"95% band holds {100 * summary.coverage:.1f}% of the seen marker coordinates ({drawn})")
    if not args.no_plot:
        plot_error_summary(summary, predictions, out_dir / "errors.png", writer=WRITER)
    print(f"wrote {len(outputs)} predictions to {out_dir}", file=sys.stderr if args.quiet else sys.stdout)


def written_here(path: Path) -> bool:
    """Whether the existing file `path` was written by `jaxspring predict` (its `writer` mark)."""
    try:
        if path.suffix.lower() == ".png":
            from PIL import Image

            with Image.open(path) as picture:
                return getattr(picture, "text", {}).get("writer") == WRITER
        import h5py

        with h5py.File(path, "r") as f:
            return f.attrs.get("writer") == WRITER
    except Exception:  # noqa: BLE001 - unreadable, truncated or of another kind: not ours
        return False


def _existing_ancestor(folder: Path) -> Path:
    """`folder`, or its nearest ancestor that exists (where `predict` will create it)."""
    folder = folder.absolute()
    while not folder.exists() and folder.parent != folder:
        folder = folder.parent
    return folder
