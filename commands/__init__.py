"""The application layer: the `detmatch` and `detmatch-export` commands.

One module per command group, each a set of thin functions that parse nothing themselves and
delegate to the layers below (`detmatch` the library, `export`, `serving`, `retrain`); this is
the only package that imports all of them, and none of them imports it. `commands.main`
assembles the `detmatch` parser from each group's `add_parsers` and dispatches;
`commands.export` is `detmatch-export`.

Imports of torch-backed modules stay inside the command functions: the `.[serve]` install has
no torch, and its `detmatch serve`, `health`, `label`, `store export` and `--version` run there.
"""
