"""Networks as plain ``nn.Module``s (Lightning wraps them in :mod:`cmlearn.surrogate.training`)."""
from .node_lstm import NodeLSTMConfig, NodeLSTMSurrogate

__all__ = ["NodeLSTMConfig", "NodeLSTMSurrogate"]
