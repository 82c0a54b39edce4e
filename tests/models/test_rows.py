import torch

from mmf_rl.models.rows import compute_on_rows


def test_selected_rows_are_computed_and_the_others_keep_their_default():
    x = torch.arange(5.0)
    mask = torch.tensor([True, False, True, False, False])
    seen = []

    def double(rows):
        seen.append(rows)
        return (2 * x[rows],)

    (out,) = compute_on_rows(mask, double, (torch.full((5,), -1.0),))
    assert out.tolist() == [0.0, -1.0, 4.0, -1.0, -1.0]
    assert seen[0].tolist() == [0, 2]


def test_all_rows_pass_the_inputs_whole_and_no_row_computes_nothing():
    x = torch.arange(3.0)
    calls = []
    (out,) = compute_on_rows(
        torch.ones(3, dtype=torch.bool), lambda rows: calls.append(rows) or (x + 1,), (torch.zeros(3),)
    )
    assert calls == [None] and out.tolist() == [1.0, 2.0, 3.0]
    (out,) = compute_on_rows(
        torch.zeros(3, dtype=torch.bool), lambda rows: calls.append(rows) or (x,), (torch.zeros(3),)
    )
    assert calls == [None] and out.tolist() == [0.0, 0.0, 0.0]


def test_gradients_reach_the_computation_through_the_scatter():
    w = torch.ones(2, requires_grad=True)
    (out,) = compute_on_rows(torch.tensor([False, True]), lambda rows: (w[rows] * 3,), (torch.zeros(2),))
    out.sum().backward()
    assert w.grad.tolist() == [0.0, 3.0]
