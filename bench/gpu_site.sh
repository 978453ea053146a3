# Sourced by bench/gpu_check.sh and bench/gpu_pong.sh on a GPU machine: installs the wheels of
# .whl/ (from bench/gpu_wheels.sh) into /tmp/site and puts it and src/ on PYTHONPATH.
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    || { echo "the wheels in .whl/ did not install (run sh bench/gpu_wheels.sh where pip can download first)"; exit 2; }
export PYTHONPATH="/tmp/site:$(pwd)/src" PYTHONUNBUFFERED=1  # absolute: tests run scripts from other folders
