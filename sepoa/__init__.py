"""The `sepoa` command: one entry point over the trainer, the server and the queue database."""
