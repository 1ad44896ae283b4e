"""Course assignments from the notebooks: student versions, a handout, a grader and a gradebook.

``python -m freereg_lib.teaching.assignments`` is the command (``make``, ``dist``, ``collect``,
``grade``, ``list``); ``assignments/README.md`` is the teacher's guide. The modules:

* :mod:`.exercises` - each exercise, its graded cases (inputs drawn per run) and the library's
  reference each answer is compared with.
* :mod:`.check` - the check cells' ``exercise_check`` and the rule a solution keeps (NumPy and
  the standard library only); the one module of this package in the students' handout.
* :mod:`.notebooks` - reading notebooks, the student versions (``make``); :mod:`.handout` -
  what students receive (``dist``).
* :mod:`.student`, :mod:`.sandbox`, :mod:`.wire` - the student's process (copied and run with
  NumPy and the standard library only), its confinement and its answers as data.
* :mod:`.grader` - the grading process: never runs student code; computes the references,
  starts one student process per submission, scores; :mod:`.gradebook` - a class at a time:
  collection, ``grades.csv`` and feedback.
"""
