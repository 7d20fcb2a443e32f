# Sourced by experiments/gpu/gpu_check.sh and gpu_train.sh, from the repository root, on a lent GPU machine where the
# repository is not installed: its areas linked into a `neumip` namespace under $site, the wheels in .whl/ (drjit)
# installed there if there are any, and the environment the runs need. Sets site and runs (where models go).
site=/tmp/neumip_site runs=/tmp/neumip_gpu_runs
mkdir -p "$site/neumip"
for area in core engines client server groundtruth training report; do ln -sfn "$PWD/$area" "$site/neumip/$area"; done
if compgen -G ".whl/*.whl" >/dev/null; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$site" .whl/*.whl
fi
export PYTHONPATH=$site PYTHONUNBUFFERED=1 OMP_WAIT_POLICY=PASSIVE
