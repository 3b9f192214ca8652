"""What a study is, below the engine that runs it (``cpgjax.ablation``): its specification (``spec``), its files
(``files``: checkpoint, trial table, recording, metadata), the robot's scene in the recording (``scene``), where its
batch runs (``placement``) and its instances as one padded batch (``batch``). The paper's studies, their reports and
the launcher are ``cpgjax.studies``."""
