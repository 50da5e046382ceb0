"""External runs: runs no worker trains, whose pairs a client pushes over REST.

The run and its tokens are in `runs`, the pushed pairs in `pairs`, the answers feed in `feed`.

An external run (`algo` "external") is created running, with no worker: a client holding a
token scoped to the run (`issue_run_token`; `revoke_run_token` ends one at once) pushes pairs
of clips (`push_pairs`), withdraws one nobody has answered yet (`withdraw_pair`: its query is
cancelled, as a closed round's are) and reads the answers people give them (`answers_after`).
Everything else is the queue's as for any run: the pairs are queries, leased and answered
through the same operations, with k answers each (`feedback.labels_per_query`), gold and
practice pairs, invites and the quality pages. A worker never claims one
(`labelqueue.runs.claim_run`).

How its answers count: an answer to an ordinary pair spends one of the run's budget (skips
and can't-tells too), counts toward a study's target and code when decisive, and is given to
the client; an answer to a gold pair costs no budget, counts toward a study's target like any
other (it looks like one) and is given to the client marked gold; a practice answer costs
nothing, counts toward nothing and is not given to the client. A push is refused once its
pairs would ask for more answers than the budget has left.

A pushed pair carries an idempotency key, unique in its run: pushing the same content under
the same key again returns the stored query; other content under a used key is refused. Its
hidden metadata (the client's own ids, true returns for the calibration report, a gold pair's
known answer) is stored beside the query and never sent to a labeller.
"""
