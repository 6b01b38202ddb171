"""The farm's two queues, emptied in this order by every worker.

``undream.control``: the start and each phase's callback (short; never wait
behind other runs' frames). ``undream.frames``: per-frame batches, first in
first out across runs.
"""
CONTROL_QUEUE = "undream.control"
FRAMES_QUEUE = "undream.frames"
QUEUES = (CONTROL_QUEUE, FRAMES_QUEUE)
