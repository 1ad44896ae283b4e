"""Report: what the notebooks draw and check (beside the method; the method never imports it).

* :mod:`.plots`: the notebooks' figures, saved small;
* :mod:`.params`: papermill parameters checked against the config's ranges, a quiet kernel;
* :mod:`.registration`: a registration's figures and the files ``freereg register`` writes;
* :mod:`.pair_files`: a pair written as a user's files (notebook 05's and the tests' inputs).
"""
