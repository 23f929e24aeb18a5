"""How the supernet evaluator batches its frames on each kind of device."""

import torch

from explorer.supernet.evaluators import frames_per_batch


def test_a_gpu_takes_each_frame_set_as_one_batch_and_a_cpu_batches_of_32():
    assert frames_per_batch(torch.device("cuda"), 256, 96) == 256
    assert frames_per_batch(torch.device("cuda:1"), 64, 96) == 96
    assert frames_per_batch(torch.device("cpu"), 256, 96) == 32
