"""``metricslam calibrate``: intrinsics and distortion from chessboard photos, as a ``--calib`` file.

Example::

    metricslam calibrate photos/ --pattern 9x6 --square-mm 25 --out my_camera.yaml
    metricslam run SEQ --calib my_camera.yaml --out est.txt

The method and how to take the photos: ``docs/calibration.md``; the fitting:
:mod:`metricslam.chessboard`.
"""

from __future__ import annotations

import argparse


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "calibrate", help="calibrate a camera from chessboard photos (writes the --calib YAML)",
        description="Finds a printed chessboard in each photo (cv2.findChessboardCorners), fits "
        "intrinsics and distortion (cv2.calibrateCamera) and writes the YAML file that "
        "`metricslam run --calib` and `metricslam camera --calib` read. See docs/calibration.md.")
    p.add_argument("images", nargs="+", metavar="IMAGE_OR_DIR",
                   help="photos of the board (files, or folders of .png/.jpg), all of one size")
    p.add_argument("--pattern", default="9x6", metavar="COLSxROWS",
                   help="inner corners per row x per column (a board of 10x7 squares is 9x6; default 9x6)")
    p.add_argument("--square-mm", type=float, default=25.0, metavar="MM", help="square side (default 25)")
    p.add_argument("--fisheye", action="store_true", help="fit OpenCV's fisheye (equidistant) model")
    p.add_argument("--out", required=True, metavar="FILE.yaml", help="calibration file to write")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    import cv2

    from metricslam.chessboard import calibrate_chessboard
    from metricslam.errors import CalibrationError, ConfigError

    try:
        cols, rows = (int(v) for v in args.pattern.lower().split("x"))
    except ValueError:
        raise ConfigError(f"--pattern must be COLSxROWS inner corners, e.g. 9x6, got {args.pattern!r}") from None
    files: list[Path] = []
    for item in map(Path, args.images):
        if item.is_dir():
            files += sorted(p for p in item.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
        else:
            files.append(item)
    if not files:
        raise ConfigError(f"no .png/.jpg photos in {args.images}")

    def read():
        for path in files:
            img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise CalibrationError("cannot read image", path)
            yield path.name, img

    result = calibrate_chessboard(read(), (cols, rows), args.square_mm / 1000.0, args.fisheye)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(result.calibration.to_yaml())
    c = result.calibration.camera
    print(f"board found in {len(result.used)} of {len(files)} photos"
          + (f" (not in: {', '.join(result.rejected)})" if result.rejected else ""))
    print(f"fx={c.fx_px:.2f} fy={c.fy_px:.2f} cx={c.cx_px:.2f} cy={c.cy_px:.2f} ({c.width_px}x{c.height_px}), "
          f"{result.calibration.distortion_model} {list(result.calibration.distortion_coefficients)}")
    print(f"RMS reprojection error {result.rms_px:.3f} px" + ("  -- above 1 px: retake blurred or "
          "badly lit photos, or check --pattern" if result.rms_px > 1.0 else ""))
    print(f"wrote {out}")
    return 0
