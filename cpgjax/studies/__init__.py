"""The studies, above the engine (``cpgjax.ablation``): the driver of any study file (``driver``), the paper studies'
reports (``registry``), the generic report of a new study (``generic``), each group's best gaits (``gaits``) and the
transfer study (``transfer``), what they report with (``stats``, ``figures``, ``video`` and its ``renderer``, the web
viewer ``viewer``) and the launcher of a study's processes (``launch``)."""
