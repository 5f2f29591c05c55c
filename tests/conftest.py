import torch

# Two threads were measured 2-10x slower than one for small models on 2-core machines.
torch.set_num_threads(1)
