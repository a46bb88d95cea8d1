# syntax=docker/dockerfile:1
# irtrack onboard image: the daemon `python -m onboard`, with the onboard runtime only (scripts/install.sh, an
# editable install of this tree in /opt/irtrack, without extras: no simulator, no plotting, no test tools --
# every one of its dependencies has a linux/aarch64 wheel; groundsim/ and bench/ are in the tree but need the
# `sim` extras to run).
# The ground simulator `python -m groundsim` needs the `sim` extras: build a second image with
# --build-arg IRTRACK_EXTRAS=sim (deploy/compose.yaml does, for its `sim` profile).
#
#   docker build -t irtrack:0.1.0 .                       (from the repository root)
#   docker build --build-arg IRTRACK_EXTRAS=sim -t irtrack-sim:0.1.0 .
#   docker run --rm --network host -v "$PWD/deploy/onboard.container.yaml:/config/onboard.yaml:ro" irtrack:0.1.0
#
# Dependencies are installed by scripts/install.sh, the same script `make test` (and so CI) runs:
# CI exercises this image's install step without a container engine.
FROM python:3.11-slim-bookworm

# Single-threaded numerics by design (one pipeline thread, one MAVLink thread): no BLAS/OpenMP/OpenCV
# thread pools competing with them for the companion computer's cores. numba loads the compiled
# kernels only from a writable cache (NUMBA_CACHE_DIR, in the /tmp tmpfs: the package tree is read-only at run
# time); the build compiles them once into IRTRACK_NUMBA_CACHE_SEED and the daemon copies that seed into the
# cache at start (onboard/app/numba_seed.py), so a start does not compile them again.
ENV PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    OPENBLAS_NUM_THREADS=1 \
    OMP_NUM_THREADS=1 \
    MKL_NUM_THREADS=1 \
    OPENCV_FOR_THREADS_NUM=1 \
    MPLCONFIGDIR=/tmp/matplotlib \
    NUMBA_CACHE_DIR=/tmp/numba-cache \
    IRTRACK_NUMBA_CACHE_SEED=/opt/numba-seed \
    IRTRACK_HEALTH_FILE=/tmp/irtrack-alive \
    PATH=/opt/venv/bin:$PATH

# Fixed uid/gid 10001 so host-side files (certificates, logs) can be chowned to it; dialout for
# serial autopilot links (/dev/ttyACM*, /dev/ttyAMA*).
RUN groupadd --system --gid 10001 irtrack \
 && useradd --system --uid 10001 --gid irtrack --groups dialout \
        --no-create-home --home-dir /nonexistent --shell /usr/sbin/nologin irtrack

WORKDIR /opt/irtrack
# Only what the install and the runtime need (README.md: the package metadata's long description).
COPY pyproject.toml README.md ./
COPY scripts/ scripts/
COPY onboard/ onboard/
COPY groundsim/ groundsim/
COPY bench/ bench/
COPY config/ config/
COPY deploy/onboard.container.yaml deploy/onboard.container.yaml

# The same install path as developers and CI; by default no extras (the onboard runtime alone), never
# the dev extras. The script ends by checking that cv2 is the contrib build with KCF. The pip cache
# mount keeps rebuilds fast and out of the image.
ARG IRTRACK_EXTRAS=""
RUN --mount=type=cache,target=/root/.cache/pip \
    bash scripts/install.sh /opt/venv "$IRTRACK_EXTRAS" \
 && python -m compileall -q onboard groundsim bench \
 && NUMBA_CACHE_DIR=/opt/numba-seed python -c "from onboard.estimation import kernels; from onboard.imaging import kernels as ik; kernels.warm(); ik.warm()" \
 && install -d -m 0755 /config \
 && cp deploy/onboard.container.yaml /config/onboard.yaml \
 && install -d -m 0755 -o 10001 -g 10001 /recordings

# /config is normally a read-only bind mount (deploy/compose.yaml); the copy above is the default: the stack's
# configuration (zenoh router on tcp/127.0.0.1:7447, MAVLink on udpin:127.0.0.1:14540), so the image alone joins
# a router and a simulator or mavlink-router on the host.  /recordings: where a volume for `record.path` goes
# (the root file system is read-only; a named volume takes this directory's owner).
# The uid alone, no group: with `uid:gid` the runtime gives the process that one group and drops the
# supplementary ones (dialout, for a serial autopilot); with the uid alone it takes the primary group and
# the supplementary ones from the image's /etc/passwd and /etc/group. Numeric, so an orchestrator's
# runAsNonRoot check sees a non-root uid without reading /etc/passwd.
USER 10001

HEALTHCHECK --interval=5s --timeout=3s --start-period=30s --retries=3 \
    CMD ["python", "-m", "onboard.health"]

STOPSIGNAL SIGTERM
ENTRYPOINT ["python", "-m", "onboard"]
CMD ["--config", "/config/onboard.yaml"]
