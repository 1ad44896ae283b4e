"""The commands: what a user runs from a shell, beside the method (the method never imports them).

* :mod:`.cli`: ``freereg register`` (also ``python -m freereg_lib``), with :mod:`.user_inputs` and
  :mod:`.inputs_check` (the user's files read and checked: bad input is one clear line);
* :mod:`.batch` (with :mod:`.batch_rows`, :mod:`.batch_files`, :mod:`.cache`) and :mod:`.cluster`:
  many pairs, resumable, on a machine or a Dask cluster;
* :mod:`.reproduce`: the notebooks run into one folder, then the book; :mod:`.book`: the book
  (Sphinx, ``book/conf.py``); :mod:`.gallery`: the README's gallery;
* :mod:`.check_weights`: are the real weights where the real backend looks;
* :mod:`.parity`, :mod:`.real_frames`, :mod:`.verdict_measure`: measurements against the
  official code's fixtures and real frames.

Each is ``python -m freereg_lib.commands.<name>``; paths default to the current folder's
``notebooks/``, ``figures/`` and ``runs/``, never to where this file lies.
"""
