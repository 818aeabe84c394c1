"""Networks as plain ``nn.Module``s (Lightning wraps the surrogates in :mod:`cmlearn.surrogate.training`;
the IQN agent is trained by :mod:`cmlearn.rl.training`)."""
from .iqn import IQNConfig, IQNNetwork, ResNetEncoder, make_iqn_actor
from .node_lstm import NodeLSTMConfig, NodeLSTMSurrogate

__all__ = ["NodeLSTMConfig", "NodeLSTMSurrogate", "IQNConfig", "IQNNetwork", "ResNetEncoder", "make_iqn_actor"]
