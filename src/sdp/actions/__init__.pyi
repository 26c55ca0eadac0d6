from ._actions import (
    PARAMETERS,
    ActionModel,
    ActionStream,
    evaluate_protocol,
    list_sequences,
    read_sequence,
    sequence_descriptor,
)
from ._splits import evaluate_splits, split_accuracies, training_sets
