"""Online learning (the paper's Algorithms 1 and 2), usable with any loop: windows of flight data, the
trainer client, the validation gate, the model monitor, honest latency, and the learner that ties them to a
``Controller``'s ticks. The trainer itself is ``cfknode.models.trainer_process``, a child process: torch runs
there and never on the flight path."""
