import os

# Test processes run side by side (./test.sh: pytest-xdist) and start pipeline subprocesses: OpenMP
# threads that spin while they wait would take the core another process needs (a --jobs 2 wave of
# 2-thread PPO ran at 0.44x of one run after the other, spinning; docs/rl.md). Set before torch loads.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402

# Two threads were measured 2-10x slower than one for small models on 2-core machines.
torch.set_num_threads(1)
