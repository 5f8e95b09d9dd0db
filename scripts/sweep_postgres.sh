#!/usr/bin/env bash
# Two sweep workers on one Optuna study in a local PostgreSQL (Optuna's own distributed mode).
# Installs Debian's postgresql if missing (apt-get) and psycopg2-binary into the venv, starts a
# throwaway server on 127.0.0.1 in a temporary folder, runs `nerfmeta sweep SPEC --storage URL`
# twice at once (each with its own --out for its run folders, as two machines would), checks that
# every planned configuration was completed exactly once with its repeats split between the two,
# and stops the server. Usage: scripts/sweep_postgres.sh [PYTHON]   (default .venv/bin/python)
set -euo pipefail
cd "$(dirname "$0")/.."
py=${1:-.venv/bin/python}
if ! ls /usr/lib/postgresql/*/bin/pg_ctl >/dev/null 2>&1; then
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq postgresql >/dev/null
fi
bin=$(ls -d /usr/lib/postgresql/*/bin | sort -V | tail -n 1)
"$py" -c "import psycopg2" 2>/dev/null || "$py" -m pip install -q --disable-pip-version-check psycopg2-binary 2>&1 | { grep -v "^WARNING: Location" || true; }
work=$(mktemp -d /tmp/sweep_pg.XXXXXX)
chmod 755 "$work"
as_pg() { if [ "$(id -u)" = 0 ]; then runuser -u postgres -- "$@"; else "$@"; fi; }
mkdir -p "$work/data" && { [ "$(id -u)" != 0 ] || chown postgres "$work/data"; }
port=$((20000 + RANDOM % 20000))
as_pg "$bin/initdb" -D "$work/data" --auth=trust -U postgres >/dev/null
as_pg "$bin/pg_ctl" -D "$work/data" -l "$work/data/server.log" -w \
    -o "-c listen_addresses=127.0.0.1 -p $port -k $work/data" start >/dev/null
trap 'as_pg "$bin/pg_ctl" -D "$work/data" -m fast stop >/dev/null; rm -rf "$work"' EXIT
as_pg "$bin/createdb" -h 127.0.0.1 -p "$port" -U postgres sweep
url="postgresql+psycopg2://postgres@127.0.0.1:$port/sweep"
"$py" -c "from nerfmeta.data.synthetic import write_tiny_scene; write_tiny_scene('$work/scene')"
cat > "$work/spec.json" <<JSON
{"scenes": ["scene"], "backbone": "grid", "name": "pg-demo",
 "fixed": {"iters": 30, "eval_every": 0, "checkpoint_every": 0, "coarse_iters": 10, "growth_steps": [],
           "num_voxels": 4000, "coarse_num_voxels": 1000, "renders": 0},
 "search": {"batch_rays": {"values": [128, 256, 512], "default": 256}, "num_voxels": {"values": [4000, 8000]}},
 "objectives": {"test_psnr": "max", "time_s": "min"}, "repeats": 2}
JSON
export OMP_NUM_THREADS=1
# The schema is made once, before the workers start (two first connections at once race to create it).
"$py" -c "import optuna, sys; optuna.storages.RDBStorage(sys.argv[1])" "$url"
"$py" -m nerfmeta sweep "$work/spec.json" --out "$work/a" --storage "$url" >"$work/a.log" 2>&1 &
a=$!
"$py" -m nerfmeta sweep "$work/spec.json" --out "$work/b" --storage "$url" >"$work/b.log" 2>&1 &
b=$!
wait $a || { tail -n 5 "$work/a.log"; exit 1; }
wait $b || { tail -n 5 "$work/b.log"; exit 1; }
"$py" - "$work" "$url" <<'PY'
import json, sys
from pathlib import Path
from nerfmeta.sweep.spec import load_spec
from nerfmeta.sweep.study import completed, open_study, open_storage, slot_of
work, url = Path(sys.argv[1]), sys.argv[2]
spec = load_spec(work / "spec.json")
study = open_study(spec, open_storage(work / "a", url), create=False)
done = completed(study)
slots = sorted(slot_of(t) for t in done)
plan = [f"p{i}" for i in range(len(spec.grid_plan()))]
fits = {d: len(list((work / d / "trials").glob("*/sweep.json"))) for d in ("a", "b")}
ok = slots == sorted(plan) and sum(fits.values()) == len(plan) * spec.repeats
print(f"postgres study: {len(done)} COMPLETE trials for {len(plan)} planned configurations (each once: {slots == sorted(plan)}); "
      f"fits run by worker a {fits['a']}, by worker b {fits['b']} (planned {len(plan) * spec.repeats}); "
      f"other trials: {sorted(t.state.name for t in study.get_trials() if t.state.name != 'COMPLETE')}")
sys.exit(0 if ok else 1)
PY
