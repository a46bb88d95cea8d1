#!/usr/bin/env bash
# One install path for developers, CI and the Dockerfile.
#   scripts/install.sh VENV_DIR [EXTRAS]     e.g. scripts/install.sh .venv sim,dev
# Creates VENV_DIR when missing and installs irtrack (editable) with its pinned ranges. No EXTRAS: the
# onboard runtime alone (the Dockerfile); sim: + the ground simulator and its plots; dev: + the test
# tools (make test / CI install sim,dev).
# opencv-contrib-python-headless is the only OpenCV wheel we allow: KCF lives in contrib,
# and a second OpenCV wheel beside it would shadow cv2. We check that at the end.
set -euo pipefail
venv="${1:-.venv}"
extras="${2:-}"
python="${PYTHON:-python3}"
if [ ! -x "$venv/bin/python" ]; then
    echo "install: creating $venv"
    "$python" -m venv "$venv"
fi
"$venv/bin/python" -m pip install --quiet --upgrade pip
spec="."
[ -n "$extras" ] && spec=".[$extras]"
# --no-compile, then compileall on every core below: pip compiles each installed module to bytecode one file at a
# time (27 s of a fresh venv's 53 s on the 2-core CI machine; 37 s in all this way). The bytecode itself is needed:
# where PYTHONDONTWRITEBYTECODE is set (this machine sets it) no import writes it, and every process the tests and
# the demo start would compile numpy, scipy and the rest again.
"$venv/bin/python" -m pip install --quiet --no-compile -e "$spec"
# TrackEval (MOT Challenge's reference reader, for the dataset tests) pins opencv-python, which would shadow
# the contrib cv2 below: dev installs take it without its dependencies (it needs only numpy, scipy, tabulate)
case ",$extras," in
    *,dev,*) "$venv/bin/python" -m pip install --quiet --no-compile --no-deps "trackeval==1.3.0" "tabulate>=0.9,<1" ;;
esac
# a file that does not compile (a package's Python 2 example) is left to compile at import, as pip leaves it; the
# packages' own test suites (a third of the files: nothing here imports them) are left out, 4 s of the step's 18
"$venv/bin/python" -m compileall -q -j 0 -x 'site-packages/.+/tests?/' $("$venv/bin/python" -c 'import sysconfig; print(" ".join(sorted({sysconfig.get_path("purelib"), sysconfig.get_path("platlib")})))') >/dev/null ||
    echo "install: some installed files did not compile to bytecode; they compile when imported"
others=$("$venv/bin/python" -m pip list --format=freeze 2>/dev/null | grep -iE '^opencv-(python|python-headless|contrib-python)==' || true)
if [ -n "$others" ]; then
    echo "install: another OpenCV wheel is installed beside opencv-contrib-python-headless:" >&2
    echo "$others" >&2
    exit 1
fi
"$venv/bin/python" -c "import cv2, sys; ok = hasattr(cv2, 'TrackerKCF') or hasattr(cv2, 'TrackerKCF_create') or hasattr(getattr(cv2, 'legacy', None), 'TrackerKCF_create'); sys.exit(0 if ok else 'install: cv2 has no KCF tracker (need opencv-contrib-python-headless)')"
echo "install: $venv ready"
