"""The application layer: workflows that drive the pipeline end to end (frame sequences in and out, the
convention diagnosis, the paper's experiment). Nothing below this layer imports it."""
