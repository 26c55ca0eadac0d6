from ._actions import (
    PARAMETERS,
    ActionModel,
    ActionStream,
    evaluate_protocol,
    list_sequences,
    read_sequence,
    sequence_descriptor,
)
