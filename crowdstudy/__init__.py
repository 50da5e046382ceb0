"""Crowd studies on the queue's tables: invite links and joining by one (`invites`), where each
participant's study stands and their completion code (`completion`), and the list to pay from
(`participants`). Only the server and the command line use it; the trainer never does."""
