"""Networks as plain ``nn.Module``s (Lightning wraps the surrogates in :mod:`cmlearn.surrogate.training` and
:mod:`cmlearn.surrogate.quasistatic_training`; the IQN agent is trained by :mod:`cmlearn.rl.training`)."""
from .iqn import IQNConfig, IQNNetwork, ResNetEncoder, make_iqn_actor
from .node_lstm import NodeLSTMConfig, NodeLSTMSurrogate
from .quasistatic import QuasiStaticConfig, QuasiStaticCorrection

__all__ = ["NodeLSTMConfig", "NodeLSTMSurrogate", "QuasiStaticConfig", "QuasiStaticCorrection", "IQNConfig",
           "IQNNetwork", "ResNetEncoder", "make_iqn_actor"]
