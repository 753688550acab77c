"""The paper's coefficient network: four parallel PReLU branches, softmax and a residual merge."""

from __future__ import annotations

import torch
from torch import nn

from .._validation import check_int

__all__ = ["PaperNetwork", "paper_parameter_count"]

#: Widths of the four branches, each layer a ``Linear`` followed by a ``PReLU``.
BRANCH_WIDTHS: tuple[tuple[int, ...], ...] = ((256, 128, 64, 32), (128, 64, 32), (64, 32), (32,))
FEATURES = 32  # width of every branch output, of the softmax and of the head input


def paper_parameter_count(n_inputs: int, n_outputs: int = 1) -> int:
    r"""Number of trainable parameters of :class:`PaperNetwork`.

    Parameters
    ----------
    n_inputs : int
        Samples per input record.
    n_outputs : int, default=1
        Regression outputs.

    Returns
    -------
    int
        :math:`480\,(n_\mathrm{in} + 1) + 55\,648 + 10 + 33\,n_\mathrm{out}`
        :math:`= 480\,n_\mathrm{in} + 56\,138 + 33\,n_\mathrm{out}`.

    Examples
    --------
    >>> from kautztwin.nn import paper_parameter_count
    >>> paper_parameter_count(900)
    488171
    """
    n_in = check_int(n_inputs, "n_inputs", minimum=1)
    n_out = check_int(n_outputs, "n_outputs", minimum=1)
    total = 0
    for widths in BRANCH_WIDTHS:
        fan_in = n_in
        for w in widths:
            total += (fan_in + 1) * w + 1  # weights, biases and one PReLU slope
            fan_in = w
    return total + (FEATURES + 1) * n_out


class PaperNetwork(nn.Module):
    r"""The paper's network from a sampled response to Kautz coefficients.

    Four parallel branches read the same input record; each is a chain of
    fully connected layers with PReLU activations whose widths halve down to
    32.  Their 32-wide outputs are summed to :math:`s`, a softmax over the 32
    features gives :math:`\sigma(s)`, the residual path adds the summed
    features back, and a linear regression head maps the result to the
    outputs:

    .. math:: \hat y = W_h\,\bigl(\sigma(s) + s\bigr) + b_h,\qquad
              s = \sum_{j=1}^{4} \mathrm{branch}_j(x).

    ======  ======================================  ==================================
    branch  layers (``Linear`` + ``PReLU`` each)    parameters
    ======  ======================================  ==================================
    1       n_in -> 256 -> 128 -> 64 -> 32          256(n_in+1) + 32 896 + 8 256 + 2 080 + 4
    2       n_in -> 128 -> 64 -> 32                 128(n_in+1) + 8 256 + 2 080 + 3
    3       n_in -> 64 -> 32                        64(n_in+1) + 2 080 + 2
    4       n_in -> 32                              32(n_in+1) + 1
    merge   sum of the four 32-wide outputs         0
    --      softmax over the 32 features, + sum     0
    head    32 -> n_out (``Linear``)                33 n_out
    ======  ======================================  ==================================

    Parameters
    ----------
    n_inputs : int
        Samples per input record (the length of the sampled response).
    n_outputs : int, default=1
        Regression outputs: 1 for one network per coefficient (as in the
        paper), ``N`` for the multi-output variant.

    Attributes
    ----------
    branches : torch.nn.ModuleList
        The four branches, each a ``torch.nn.Sequential`` of alternating
        ``Linear`` and ``PReLU`` layers.
    head : torch.nn.Linear
        The regression layer ``Linear(32, n_outputs)``.
    n_inputs, n_outputs : int
        The sizes given.

    Raises
    ------
    DataError
        If a size is not a positive integer.

    See Also
    --------
    paper_parameter_count : The parameter count as a function of the sizes.
    kautztwin.nn.CoefficientEstimator : Trains these networks on labelled responses.

    Notes
    -----
    Every PReLU has one learnable slope shared by its channels (the PyTorch
    default, initialised to 0.25), so the network has exactly

    .. math:: 480\,(n_\mathrm{in} + 1) + 55\,648 + 10 + 33\,n_\mathrm{out}

    trainable parameters: 488 171 for the paper's 900-sample records and one
    output.  The input layers (``480 (n_in + 1)``) hold about 89 % of them.

    Examples
    --------
    >>> import torch
    >>> from kautztwin.nn import PaperNetwork
    >>> net = PaperNetwork(900)
    >>> sum(p.numel() for p in net.parameters())
    488171
    >>> net(torch.zeros(5, 900)).shape
    torch.Size([5, 1])
    """

    def __init__(self, n_inputs: int, n_outputs: int = 1) -> None:
        super().__init__()
        self.n_inputs = check_int(n_inputs, "n_inputs", minimum=1)
        self.n_outputs = check_int(n_outputs, "n_outputs", minimum=1)
        branches = []
        for widths in BRANCH_WIDTHS:
            layers: list[nn.Module] = []
            fan_in = self.n_inputs
            for w in widths:
                layers += [nn.Linear(fan_in, w), nn.PReLU()]
                fan_in = w
            branches.append(nn.Sequential(*layers))
        self.branches = nn.ModuleList(branches)
        self.head = nn.Linear(FEATURES, self.n_outputs)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """Summed branch outputs :math:`s` (before the softmax).

        Parameters
        ----------
        x : torch.Tensor of shape (batch, n_inputs)

        Returns
        -------
        torch.Tensor of shape (batch, 32)
        """
        s = self.branches[0](x)
        for branch in self.branches[1:]:
            s = s + branch(x)
        return s

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Predict from a batch of records.

        Parameters
        ----------
        x : torch.Tensor of shape (batch, n_inputs)
            Input records (normalised by the caller).

        Returns
        -------
        torch.Tensor of shape (batch, n_outputs)
        """
        s = self.features(x)
        return self.head(torch.softmax(s, dim=-1) + s)

    def extra_repr(self) -> str:
        return f"n_inputs={self.n_inputs}, n_outputs={self.n_outputs}"
