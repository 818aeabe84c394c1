"""Every test starts from the same random state, so a test that draws random inputs is reproducible.
Under pytest-xdist each worker (and every script a test starts) runs torch on one thread, so the workers
share the cores instead of oversubscribing them."""
import os

import numpy as np
import pytest
import torch

if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ["OMP_NUM_THREADS"] = "1"  # inherited by the scripts the tests start
    torch.set_num_threads(1)


@pytest.fixture(autouse=True)
def _seed_everything():
    torch.manual_seed(0)
    np.random.seed(0)
    yield
