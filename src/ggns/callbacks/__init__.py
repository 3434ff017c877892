"""Every Lightning callback of the library, in one package (config class paths: `ggns.callbacks.<Name>`).

Rollouts (`evaluation.py`; they roll out through the model's step and the one engine, the model knows
none of them):
    RolloutEvaluation   validation rollout metrics, one scalar per metric family (checkpoint selection)
    TestEvaluation      the test's rollouts, metrics and report (the CLI's `evaluation:` group)
    RolloutPictures     truth against rollout in TensorBoard
    RolloutWriter       predict's rollouts as a predictions file
Speed (`speed.py`, docs/speed.md): StaticRollouts, StaticTraining, MatmulPrecision, CompileProcessor.
Runs: RandomState (`random_state.py`: a resumed fit repeats the uninterrupted one), TrainingClock
(`clock.py`: training seconds without validation), RunConfigCallback, LastCheckpointOnSigterm and
InitialWeights (`run.py`: the command line's saved config, SIGTERM checkpoint, and a fit that starts from a
trained checkpoint's weights). `ggns.cli` adds RandomState, TestEvaluation,
LastCheckpointOnSigterm and a LearningRateMonitor to every run.
"""
from .clock import TrainingClock
from .evaluation import RolloutEvaluation, RolloutPictures, RolloutWriter, TestEvaluation, TestedCheckpoint, TestReport
from .random_state import RNG_KEY, RandomState
from .run import InitialWeights, LastCheckpointOnSigterm, RunConfigCallback
from .speed import CompileProcessor, MatmulPrecision, StaticRollouts, StaticTraining

__all__ = ["CompileProcessor", "InitialWeights", "LastCheckpointOnSigterm", "MatmulPrecision", "RNG_KEY", "RandomState", "RolloutEvaluation",
           "RolloutPictures", "RolloutWriter", "RunConfigCallback", "StaticRollouts", "StaticTraining", "TestEvaluation",
           "TestReport", "TestedCheckpoint", "TrainingClock"]
