"""`planeslam bench speed DATASET --no-synthetic` for an older checkout whose CLI has no
`bench speed` (docs/speed.md, "The run's end"): its code, timed by this checkout's
benchmark.

    git worktree add --detach ../wt-e7c e7c0351
    cp planeslam/app/bench.py planeslam/app/bench_speed.py ../wt-e7c/planeslam/app/
    ln -s ../factors ../wt-e7c/planeslam/factors  # its own factors, not this install's
    PYTHONPATH=../wt-e7c python docs/scripts/bench_speed_checkout.py \
        ../shared/data/7scenes_redkitchen_1000f

The symbolic link matters: an editable install of this checkout maps `planeslam.factors`
to its own `factors/` folder, which the older code would otherwise import.
"""

from __future__ import annotations

import sys

from planeslam.app.bench_speed import bench_speed
from planeslam.core.native_tuning import keep_freed_memory

if __name__ == "__main__":
    keep_freed_memory()  # as the CLI does
    command = "python docs/scripts/bench_speed_checkout.py " + " ".join(sys.argv[1:])
    print(bench_speed(sys.argv[1:], synthetic=False, command=command).to_text())
