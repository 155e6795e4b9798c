"""The scene worker process (``systems/scene_worker.py``): builds the rigid scene's
plant exactly as ``AddScene`` does in place (``SceneStepper``) and serves the
parent's requests.

Run as ``python -m maglev_haptics.diagrams.scene_process MEMORY_FD WAKE_FD`` with
the shared memory's and the wake-up eventfd's file descriptors and, pickled on
standard input, (scene config, time step (s), X_WI_start as a 4x4 matrix).
"""

import mmap
import pickle
import sys

import numpy as np
from pydrake.math import RigidTransform

from maglev_haptics.diagrams.scene_builder import SceneStepper
from maglev_haptics.systems.scene_worker import SharedBlock, serve


def main() -> None:
    memory_fd, wake_fd = int(sys.argv[1]), int(sys.argv[2])
    scene, time_step_s, X_WI_start = pickle.load(sys.stdin.buffer)
    stepper = SceneStepper(scene, time_step_s, RigidTransform(np.asarray(X_WI_start)))
    memory = mmap.mmap(memory_fd, SharedBlock.size(stepper.n))
    serve(SharedBlock(memory, stepper.n), wake_fd, stepper)


if __name__ == "__main__":
    main()
