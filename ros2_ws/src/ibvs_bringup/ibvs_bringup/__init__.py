"""Launch files, parameters, runner, bag record/replay, plots and reports of the IBVS stack."""
