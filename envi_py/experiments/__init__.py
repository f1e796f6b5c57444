"""The paper's use cases as a reproducible grid: :mod:`.grid` (which logs), :mod:`.executor` (local
processes or Dask), :mod:`.worker` (one training and its verification), :mod:`.report` (tables and
plots), :mod:`.run` (all of it), :mod:`.cli` (``envi experiment``)."""
