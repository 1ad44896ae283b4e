"""Course assignments from the notebooks: student versions, a student distribution and a grader.

``python -m freereg_lib.teaching.assignments`` is the command (``make``, ``dist``, ``grade``, ``list``);
``assignments/README.md`` is the teacher's guide. The modules, imported one way only:

* :mod:`.exercises` - the registry: each exercise, its graded cases (inputs drawn from the
  grader's secret seed) and the library reference each is compared with;
  :class:`~.exercises.exercise_check` for the notebooks' check cells.
* :mod:`.notebooks` - reading notebooks, the student versions (``make``) and the student
  distribution without answer keys (``dist``).
* :mod:`.wire` - answers and inputs as data (npz arrays and JSON numbers; never pickles).
* :mod:`.poison` - the library's reference functions as the student's process sees them:
  deliberately altered, so a solution that calls them gives itself away.
* :mod:`.sandbox` - resource limits, Landlock file-system confinement and the killing of
  everything a student's process started.
* :mod:`.student` - the student's process: runs the solution cells, answers the grader's
  inputs, writes the answers as data. Nothing else.
* :mod:`.grader` - the grading process: never runs student code; draws the inputs, computes
  the references, starts one student process per submission, scores the answers.
"""
