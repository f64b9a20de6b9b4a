"""Relabel a state-only LeRobot dataset with the inverse dynamics model (IDM) of a trained IUPE checkpoint (a
full IUPE run's, or a ``--policy.supervised=true`` one trained on any labelled dataset of the same robot).

Every frame t with a successor gets ``action = IDM(s_{t-k} … s_{t+1+k})`` (k = the checkpoint's ``idm_context``;
k = 0 is the pair (s_t, s_{t+1})): an action id (int64) for a discrete IDM, a float32 vector with the checkpoint's
action names for a continuous one. The last frame of an episode has no successor; it repeats the label of the
frame before it (an episode of a single frame gets action 0). Episodes are labelled in spans that never cross an
episode, so the labels do not depend on how episodes are shared among processes (``torchrun``). The dataset is
rewritten beside itself and swapped in only when complete (``data.storage.staged_directory``): the original
survives any failure or kill.

The parts: ``config`` (the command's flags and report), ``checks`` (the checkpoint and whether it can label the
dataset), ``labelling`` (the IDM over every episode, on one or several processes), ``writing`` (the labels into a
copy of the dataset) and ``run`` (all of it, under the dataset's one-writer lock).
"""

from lerobot_iupe.relabel.config import CheckpointRef, RelabelConfig, RelabelDataset, RelabelReport
from lerobot_iupe.relabel.run import relabel

__all__ = ["CheckpointRef", "RelabelConfig", "RelabelDataset", "RelabelReport", "relabel"]
