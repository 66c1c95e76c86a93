"""Online learning (the paper's Algorithms 1 and 2), usable with any loop: windows of flight data, the
trainer process and its client, the validation gate, the model monitor, honest latency, and the learner that
ties them to a ``Controller``'s ticks. Torch runs only in the trainer process."""
