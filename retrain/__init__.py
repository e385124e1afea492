"""Retraining rounds: the label store's frames feed the next model version (`detmatch retrain`).

A round reads every shard of the label store (`retrain.data`), continues teacher-student
training from the promoted version's checkpoint, scores the candidate and the promoted version
on the same held-out gate split (`retrain.gate`), exports the candidate and promotes it only if
it does not regress (`retrain.round`), and writes a report (`retrain.report`). `retrain.schedule`
runs rounds every so often under a lock. `retrain.demo` is `detmatch demo`, the whole product
in one command.

Above `detmatch` (training), `export` and `serving` (store, repository): it is the one place
that joins them, as the command line does.
"""
