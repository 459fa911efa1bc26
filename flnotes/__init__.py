"""flnotes: constrained feedback linearization with ReLU networks encoded as MILPs."""
from .config import FAST, scale
from .systems import FLSystem, brunovsky, discretize, msd, quad1d
from .network import ReLUNet, TrainingReport, fit_relu, uniform_grid
from .bounds import NodeBounds, fbbt, interval_affine, sample_preactivations
from .encoding import BigMForm, Encoding, bigm_form, encode, forward_milp
from .simulate import Controller, FeedbackLaw, SimLog, StepResult, simulate
from . import paper
from .paper import paper_net
