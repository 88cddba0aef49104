# ttompc on CPU, installed exactly like CI (.ci/run -> `make test` -> `make install`): a virtual environment with
# CPU torch 2.13.0 first (a bare `torch` would resolve to a multi-GB CUDA build), then the package and its extras.
#   docker build -t ttompc .
#   docker run --rm ttompc demo          # the quickstart main job (offline)
#   docker run --rm ttompc solve --scenario rpod --seed 3
FROM python:3.11-slim

ENV PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_NO_CACHE_DIR=1 \
    WANDB_MODE=offline HF_HUB_OFFLINE=1 HF_DATASETS_OFFLINE=1 MPLBACKEND=Agg

RUN apt-get update -qq && apt-get install -y -qq --no-install-recommends make git && rm -rf /var/lib/apt/lists/*

WORKDIR /opt/ttompc
COPY . .
RUN make install TORCH_PIP_ARGS="--index-url https://download.pytorch.org/whl/cpu"
# compile the Riccati kernel of the default solver path into numba's on-disk cache inside the image, so that containers
# load it instead of each compiling it (~20 s); on a CPU other than the build machine's each container compiles again
RUN .venv/bin/ttompc solve --scenario freeflyer >/dev/null && .venv/bin/ttompc solve --scenario quadrotor >/dev/null

ENTRYPOINT ["/opt/ttompc/.venv/bin/ttompc"]
CMD ["--help"]
