"""Edge Gumbel Selector (docs/MODEL.md 2.1): each target samples at most n neighbours.

The number of edge heads n is a traced value. The 128-wide q/k/v are split into
G = config.head_slots groups of width 128/G; head h of an n-head model owns the G/n consecutive
groups starting at h G/n, so its dot products are sums over its groups and its slice of
q/k/v is exactly the release's head h. The shared per-head MLP Linear(hd, hd) lives in the
top-left hd x hd block of a 128 x 128 weight and is applied to all heads at once as a
block-diagonal matrix. One parameter layout and one compiled program serve every n | G.

Nothing 128-wide is formed per edge except the MLP's hidden layer. phi_e is affine in the
2-d edge feature A, so LayerNorm(phi_e(A)) W_c is c_ij @ basis with 4 coefficients per edge
(A / std, 1 / std, 1) and a (4, 3W) basis. Each edge's q/k/v is then a per-neighbour part
plus an affine combination of 5 per-target vectors, and the attention scores and the
value mixture are contracted through those parts (plus the MLP's first, linear layer,
applied to the value parts before mixing): the same maths, with per-edge work of width 5
instead of 3W = 384.

With a candidate neighbourhood (`ModelConfig.candidates` = k, docs/MODEL.md 2.4) each target
attends over its own K = min(k, N) candidates and the ghost only: the neighbour parts, edge
coefficients and validity are gathered per target, (..., N, K+1, ...), the same contractions
run with a target axis on them, and the probabilities are scattered back to all N + 1
neighbours, zero outside the candidates, so that sampling and everything after it are those
of the exact model. Per step the attention is then (N, G, K+1, K+1) instead of
(N, G, N+1, N+1): N K^2 work instead of N^3.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from gst_jax.config import ModelConfig
from gst_jax.graph import ATTENTION_WEIGHTS, EPS, masked_categorical
from gst_jax.gumbel import gumbel_softmax
from gst_jax.model.controls import Controls
from gst_jax.model.layers import Dropout, LayerNormParams, layer_norm, torch_uniform


def nearest_candidates(edge_features: jax.Array, node_mask: jax.Array, count: int) -> jax.Array:
    """Each target's candidate neighbourhood (docs/MODEL.md 2.4): (..., N, K) the slots of its
    K = min(count, N) nearest valid people, nearest first and itself first of all (its self
    edge is in the adjacency); equal distances go to the lower slot. A target with fewer than
    K valid people gets invalid slots too, which the adjacency masks.

    edge_features (..., N, N, 2) A indexed [j, i]; node_mask (..., N). The choice is not
    differentiable and takes no gradient.
    """
    offsets = jax.lax.stop_gradient(jnp.swapaxes(edge_features, -2, -3))     # [i, j]
    num_nodes = node_mask.shape[-1]
    valid = (node_mask[..., :, None] * node_mask[..., None, :]) > 0
    distance = jnp.where(valid, offsets[..., 0] ** 2 + offsets[..., 1] ** 2, jnp.inf)
    distance = jnp.where(jnp.eye(num_nodes, dtype=bool), -1.0, distance)
    return jax.lax.top_k(-distance, min(count, num_nodes))[1]


def with_ghost(candidates: jax.Array, num_nodes: int) -> jax.Array:
    """(..., K) candidate slots -> (..., K+1) with the ghost's, N, last."""
    ghost = jnp.full(candidates.shape[:-1] + (1,), num_nodes, candidates.dtype)
    return jnp.concatenate([candidates, ghost], axis=-1)


def gather_neighbours(per_neighbour: jax.Array, neighbours: jax.Array) -> jax.Array:
    """Each target's own rows: per_neighbour (..., L, F), neighbours (..., N, K)
    -> (..., N, K, F)."""
    return jnp.take_along_axis(per_neighbour[..., None, :, :], neighbours[..., None], axis=-2,
                               mode="clip")


def scatter_neighbours(per_candidate: jax.Array, candidates: jax.Array,
                       num_nodes: int) -> jax.Array:
    """(..., K+1) values of each target's candidates then the ghost -> (..., N+1) over every
    neighbour (ghost last), zero outside the candidates. candidates (..., K) broadcasts
    against per_candidate's leading axes."""
    slots = with_ghost(
        jnp.broadcast_to(candidates, per_candidate.shape[:-1] + candidates.shape[-1:]), num_nodes)
    every = jnp.zeros(per_candidate.shape[:-1] + (num_nodes + 1,), per_candidate.dtype)
    return jnp.put_along_axis(every, slots, per_candidate, axis=-1, inplace=False)


def group_to_head(num_groups: int, num_edge_heads: jax.Array) -> jax.Array:
    """(G, G) 0/1 matrix: entry [g, h] = 1 iff group g belongs to active head h < n."""
    groups_per_head = num_groups // jnp.maximum(num_edge_heads, 1)
    group = jnp.arange(num_groups)
    head = jnp.arange(num_groups)
    owner = group // groups_per_head
    owned = (owner[:, None] == head[None, :]) & (head[None, :] < num_edge_heads)
    return owned.astype(jnp.float32)


def block_diagonal(weight: jax.Array, head_dim: jax.Array) -> jax.Array:
    """Repeat the top-left head_dim x head_dim block of a (W, W) weight along the diagonal."""
    width = weight.shape[0]
    within = jnp.arange(width) % head_dim
    block = jnp.arange(width) // head_dim
    same_block = block[:, None] == block[None, :]
    return jnp.where(same_block, weight[within[:, None], within[None, :]], 0.0)


class EdgeSelector(nn.Module):
    """Scores every (target, neighbour) edge and samples n neighbours per target."""

    config: ModelConfig

    def setup(self):
        config = self.config
        width = config.selector_dim
        init_heads = max(config.num_edge_heads, 1)
        head_dim = width // init_heads
        self.norm_node = layer_norm()
        self.norm_edge = LayerNormParams(config.edge_dim)
        # torch.nn.MultiheadAttention's in_proj: xavier-uniform weight, zero bias.
        self.in_proj_kernel = self.param("in_proj_kernel", nn.initializers.xavier_uniform(),
                                         (width, 3 * width))
        self.in_proj_bias = self.param("in_proj_bias", nn.initializers.zeros, (3 * width,))
        # The per-head MLP, padded: only the top-left head_dim block is used.
        self.mlp_hidden_kernel = self.param("mlp_hidden_kernel", torch_uniform(head_dim),
                                            (width, width))
        self.mlp_hidden_bias = self.param("mlp_hidden_bias", torch_uniform(head_dim), (width,))
        self.mlp_out_kernel = self.param("mlp_out_kernel", torch_uniform(head_dim), (width,))
        self.mlp_out_bias = self.param("mlp_out_bias", torch_uniform(head_dim), ())
        self.dropout = Dropout(config.dropout, ghost_axis=-2)      # (..., N, L, W)

    def edge_coefficients(self, a: jax.Array, valid: jax.Array,
                          edge_embedding: tuple[jax.Array, jax.Array],
                          ) -> tuple[jax.Array, jax.Array]:
        """a_ij LayerNorm(phi_e(A[j, i])) W_c per target i and neighbour j, as c_ij @ basis.

        a (..., N, M, 2): A[j, i] indexed [i, j] over M neighbours (all N, or each target's
        candidates); valid (..., N, M): a_ij; edge_embedding: phi_e's (kernel (2, d_e), bias
        (d_e,)). Returns the coefficients c (..., N, M+1, 4) indexed [i, j] (ghost column zero)
        and the basis (4, 3W).
        """
        kernel, bias = edge_embedding
        scale, shift = self.norm_edge()
        edge_kernel = self.in_proj_kernel[2 * self.config.node_dim:]              # W_c (d_e, 3W)
        centred_kernel = kernel - kernel.mean(axis=-1, keepdims=True)            # (2, d_e)
        centred_bias = bias - bias.mean()
        # LayerNorm variance of A K + b over d_e features, as a quadratic form in A.
        gram = centred_kernel @ centred_kernel.T / kernel.shape[-1]              # (2, 2)
        cross = centred_kernel @ centred_bias / kernel.shape[-1]                 # (2,)
        offset = centred_bias @ centred_bias / kernel.shape[-1]
        variance = (jnp.einsum("...p,pq,...q->...", a, gram, a) + 2 * a @ cross + offset)
        scaled = jax.lax.rsqrt(jnp.maximum(variance, 0.0) + 1e-5) * valid        # (..., N, M)
        coefficients = jnp.stack([a[..., 0] * scaled, a[..., 1] * scaled, scaled, valid], -1)
        coefficients = jnp.concatenate([coefficients, jnp.zeros_like(coefficients[..., :1, :])],
                                       axis=-2)
        basis = jnp.stack([centred_kernel[0] * scale @ edge_kernel,
                           centred_kernel[1] * scale @ edge_kernel,
                           (centred_bias * scale) @ edge_kernel,
                           shift @ edge_kernel])
        return coefficients, basis

    def __call__(self, node_embedding: jax.Array, edge_features: jax.Array,
                 edge_embedding: tuple[jax.Array, jax.Array], adjacency: jax.Array,
                 controls: Controls, *, deterministic: bool,
                 candidates: jax.Array | None = None) -> jax.Array:
        """Edge probabilities of one or more time steps (sample them with `sample_edges`).

        node_embedding: (..., N, d) phi_v(v); edge_features: (..., N, N, 2) A indexed [j, i];
        edge_embedding: phi_e's (kernel, bias); adjacency: (..., N, N) a_ij; candidates:
        (..., N, K) each target's candidate neighbours (`nearest_candidates`), None = all.
        Returns edge_probs (..., N, G, N+1): target, head slot, neighbour (ghost last);
        inactive head slots, invalid neighbours and non-candidates zero.
        """
        config = self.config
        num_groups = config.head_slots
        width = config.selector_dim
        d = config.node_dim
        n = controls.num_edge_heads
        head_dim = width // jnp.maximum(n, 1)

        node_valid = jnp.diagonal(adjacency, axis1=-2, axis2=-1)                # (..., N)
        x = self.norm_node(node_embedding) * node_valid[..., None]
        # The ghost neighbour: zero node and edge features, valid for every target.
        x_nb = jnp.concatenate([x, jnp.zeros_like(x[..., :1, :])], axis=-2)     # (..., L, d)
        ghost_column = jnp.broadcast_to(controls.ghost.astype(x.dtype), node_valid.shape)
        a, valid = jnp.swapaxes(edge_features, -2, -3), jnp.swapaxes(adjacency, -1, -2)  # [i, j]
        if candidates is not None:
            # Only the candidates are neighbours: every per-edge array is gathered per target,
            # and the neighbour axis L below is each target's K candidates and the ghost.
            a = jnp.take_along_axis(a, candidates[..., None], axis=-2, mode="clip")  # (.., N, K, 2)
            valid = jnp.take_along_axis(valid, candidates, axis=-1, mode="clip")     # (.., N, K)
        valid_edges = jnp.concatenate([valid, ghost_column[..., None]], axis=-1)  # a'_ij (.., N, L)

        # [x_j | x_i | e_ji] W = x_j W_a + (x_i W_b + bias) + c_ij @ basis: a per-neighbour
        # part P_j, and per target i an affine combination of R = 5 vectors B_i with the edge
        # coefficients c~_ij = (1, c_ij). Scores and values are contracted through these
        # parts, so no per-edge q/k/v is ever formed.
        kernel = self.in_proj_kernel
        from_neighbour = x_nb @ kernel[:d]                                       # (..., L, 3W)
        from_target = x @ kernel[d:2 * d] + self.in_proj_bias                    # (..., N, 3W)
        coefficients, edge_basis = self.edge_coefficients(a, valid, edge_embedding)
        c = jnp.concatenate([jnp.ones_like(coefficients[..., :1]), coefficients],
                            axis=-1)                                             # (..., N, L, R)
        # The MLP's first layer is linear in the attention output, so it is applied to the
        # values' parts before they are mixed (block-diagonal: each head's own weight).
        mlp_hidden = block_diagonal(self.mlp_hidden_kernel, head_dim)

        def through_mlp(t):  # (..., 3W): the value part times the MLP's first layer
            return jnp.concatenate([t[..., :2 * width], t[..., 2 * width:] @ mlp_hidden], axis=-1)

        node_part = through_mlp(from_neighbour)                                  # (..., L, 3W)
        target_part = through_mlp(from_target)                                   # (..., N, 3W)
        edge_basis = through_mlp(edge_basis)                                     # (R - 1, 3W)

        def grouped(t):  # (..., 3W) -> q, k, v parts, each (..., G, W/G)
            t = t.reshape(t.shape[:-1] + (3, num_groups, width // num_groups))
            return t[..., 0, :, :], t[..., 1, :, :], t[..., 2, :, :]

        heads = group_to_head(num_groups, n)                                     # (G, G)
        scale = jnp.sqrt(head_dim.astype(x.dtype))
        if candidates is not None:
            hidden = _candidate_hidden(grouped(node_part), grouped(target_part),
                                       grouped(edge_basis), c, valid_edges, n, scale,
                                       with_ghost(candidates, x.shape[-2]), config.attention)
        else:
            pq, pk, pv = grouped(node_part)                                      # (..., L, G, w)
            basis = jnp.concatenate([target_part[..., None, :], jnp.broadcast_to(
                edge_basis, target_part.shape[:-1] + edge_basis.shape)], axis=-2)  # (..., N, R, 3W)
            bq, bk, _ = grouped(basis)                                           # (..., N, R, G, w)
            # q_il . k_im = P_l.P_m + c~_im.(B_i.P_l) + c~_il.(B_i.P_m) + c~_il (B_i.B_i) c~_im
            pq_bk = jnp.einsum("...lgc,...isgc->...igls", pq, bk)
            bq_pk = jnp.einsum("...irgc,...mgc->...igrm", bq, pk)
            bq_bk = jnp.einsum("...irgc,...isgc->...igrs", bq, bk)
            by_target = pq_bk + jnp.einsum("...ilr,...igrs->...igls", c, bq_bk)
            group_scores = (jnp.einsum("...lgc,...mgc->...glm", pq, pk)[..., None, :, :, :]
                            + jnp.einsum("...igls,...ims->...iglm", by_target, c)
                            + jnp.einsum("...ilr,...igrm->...iglm", c, bq_pk))  # (..., N, G, L, L)
            group_weights, mixed_coefficients = _attend(group_scores, c, valid_edges, n, scale,
                                                         config.attention)
            # The values' basis B_i is the target's own part and R - 1 parts shared by every
            # target (and sample): contracted with the shared parts in one product for all edges.
            own_values = grouped(target_part)[2]                                 # (..., N, G, w)
            shared_values = grouped(edge_basis)[2]                               # (R - 1, G, w)
            # (..., N, L, G, 1)
            own_weights = jnp.swapaxes(mixed_coefficients[..., 0], -1, -2)[..., None]
            hidden = (jnp.einsum("...iglm,...mgc->...ilgc", group_weights, pv)
                      + own_weights * own_values[..., None, :, :]
                      + jnp.einsum("...gls,sgc->...lgc", mixed_coefficients[..., 1:],
                                   shared_values))
        hidden = hidden.reshape(hidden.shape[:-2] + (width,))                    # (..., N, L, W)

        within = jnp.arange(width) % head_dim
        hidden = nn.relu(hidden + self.mlp_hidden_bias[within])
        hidden = self.dropout(hidden, deterministic=deterministic)
        # The MLP's output layer, per group: a (W, G) matrix, so that this is one dot.
        channel_group = jnp.arange(width) // (width // num_groups)
        output_by_group = jnp.where(channel_group[:, None] == jnp.arange(num_groups),
                                    self.mlp_out_kernel[within][:, None], 0.0)
        contributions = hidden @ output_by_group                                 # (..., N, L, G)
        logits = jnp.einsum("...lg,gh->...hl", contributions, heads) + self.mlp_out_bias

        edge_probs = (masked_categorical(logits, valid_edges[..., None, :], config.attention)
                      * _active_heads(controls, num_groups))
        if candidates is None:
            return edge_probs
        return scatter_neighbours(edge_probs, candidates[..., None, :], x.shape[-2])


def head_totals(per_group: jax.Array, num_edge_heads: jax.Array, axis: int) -> jax.Array:
    """Each group's head total along `axis` (G groups): the sum over the G/n consecutive groups
    of its head, the same for every group of a head.

    G and n are powers of two (G divides the 128-wide selector, n divides G), so the totals
    are a butterfly: at stride s = 1, 2, ... < G/n each group adds the partial total of group
    g XOR s. Every level is an elementwise add of a static permutation of the G axis; a
    contraction with a (G, G) group-to-head matrix did the same on a CPU in several times the
    time, most of it transposing G to the end and back. With n = G nothing is added.
    """
    axis = axis % per_group.ndim
    num_groups = per_group.shape[axis]
    groups_per_head = num_groups // jnp.maximum(num_edge_heads, 1)
    total, stride = per_group, 1
    while stride < num_groups:
        blocks = (total.shape[:axis] + (num_groups // (2 * stride), 2, stride)
                  + total.shape[axis + 1:])
        partner = jnp.flip(total.reshape(blocks), axis=axis + 1).reshape(total.shape)
        total = total + jnp.where(stride < groups_per_head, partner, 0.0)
        stride *= 2
    return total


def _attend(group_scores: jax.Array, c: jax.Array, valid_edges: jax.Array,
            num_edge_heads: jax.Array, scale: jax.Array, attention: str
            ) -> tuple[jax.Array, jax.Array]:
    """The attention among each target's neighbours (docs/MODEL.md 2.1 steps 4-5), per group:
    group_scores (..., N, G, L, L), c (..., N, L, R), valid_edges (..., N, L), attention the
    `ModelConfig.attention` kind. Returns the
    weights (..., N, G, L, L), each group its head's, and the coefficients they mix,
    sum_m w_ilm c~_im (..., N, G, L, R)."""
    scores = head_totals(group_scores, num_edge_heads, axis=-3) / scale
    edge_pair_mask = valid_edges[..., None, :, None] * valid_edges[..., None, None, :]
    group_weights = ATTENTION_WEIGHTS[attention](scores, edge_pair_mask)         # (..., N, G, L, L)
    return group_weights, jnp.einsum("...glm,...ms->...gls", group_weights, c)


def _candidate_hidden(node, target, shared, c: jax.Array, valid_edges: jax.Array,
                      num_edge_heads: jax.Array, scale: jax.Array, neighbours: jax.Array,
                      attention: str) -> jax.Array:
    """`EdgeSelector`'s attention and value mixture over each target's candidates: the exact
    model's maths with l, m over the K+1 neighbours of `neighbours` (..., N, K+1) (candidates,
    then the ghost) and c, valid_edges gathered likewise. node (P_q, P_k, P_v) (..., N+1, G, w)
    of every neighbour, target (T_q, T_k, T_v) (..., N, G, w) and shared (E_q, E_k, E_v)
    (R-1, G, w) are the parts of q, k, v (B_i = [T_i; E]). Returns the MLP's hidden layer
    before its bias, (..., N, K+1, G, w).

    Products with the neighbours' q/k parts are formed densely over all N + 1 of them (N^2 w
    multiply-adds in a few matrix products) and gathered after; only the value parts are
    gathered per edge. The small sums over R run as elementwise products. Both keep every
    per-target matrix product in its natural layout: gathering the q/k parts per edge and
    contracting everything with einsum took several times longer on a CPU, in transposes.
    """
    (pq, pk, pv), (tq, tk, tv), (eq, ek, ev) = node, target, shared
    num_neighbours = pq.shape[-3]

    def per_target(rows):  # (..., N+1, G, X) -> (..., N, G, K+1, X): each target's candidates
        flat = gather_neighbours(rows.reshape(rows.shape[:-2] + (-1,)), neighbours)
        return jnp.swapaxes(flat.reshape(flat.shape[:-1] + rows.shape[-2:]), -3, -2)

    def by_neighbour(per_target_row):  # (..., N, G, N+1) -> (..., N, G, K+1)
        return jnp.take_along_axis(per_target_row, neighbours[..., None, :], axis=-1, mode="clip")

    # q_il . k_im = P_l.P_m + c~_im.(B_i.P_l) + c~_il.(B_i.P_m) + c~_il (B_i.B_i) c~_im, with
    # the first three products dense over all neighbours, then gathered.
    gram = jnp.einsum("...lgc,...mgc->...glm", pq, pk)                          # (..., G, N+1, N+1)
    pairs = neighbours[..., :, None] * num_neighbours + neighbours[..., None, :]
    node_scores = jnp.take_along_axis(
        gram.reshape(gram.shape[:-2] + (-1,))[..., None, :, :],
        pairs.reshape(pairs.shape[:-2] + (1, -1)), axis=-1, mode="clip").reshape(
            pairs.shape[:-2] + (gram.shape[-3],) + pairs.shape[-2:])            # (..., N, G, L, L)
    pq_bk = jnp.concatenate([
        by_neighbour(jnp.einsum("...lgc,...igc->...igl", pq, tk))[..., None],
        per_target(jnp.einsum("...lgc,sgc->...lgs", pq, ek))], axis=-1)        # (..., N, G, L, R)
    bq_pk = jnp.concatenate([
        by_neighbour(jnp.einsum("...igc,...mgc->...igm", tq, pk))[..., None, :],
        jnp.swapaxes(per_target(jnp.einsum("rgc,...mgc->...mgr", eq, pk)), -1, -2)],
        axis=-2)                                                                 # (..., N, G, R, L)
    own = jnp.concatenate([jnp.einsum("...igc,...igc->...ig", tq, tk)[..., None],
                           jnp.einsum("...igc,sgc->...igs", tq, ek)], axis=-1)  # (..., N, G, R)
    others = jnp.concatenate([
        jnp.einsum("rgc,...igc->...igr", eq, tk)[..., None],
        jnp.broadcast_to(jnp.einsum("rgc,sgc->grs", eq, ek), own.shape[:-1] + eq.shape[:1]
                         + ek.shape[:1])], axis=-1)                             # (.., N, G, R-1, R)
    bq_bk = jnp.concatenate([own[..., None, :], others], axis=-2)               # (..., N, G, R, R)
    c = c[..., None, :, :]                                                       # (..., N, 1, L, R)
    by_target = pq_bk + jnp.einsum("...glr,...grs->...gls", c, bq_bk)
    group_scores = (node_scores + jnp.einsum("...gls,...gms->...glm", by_target, c)
                    + jnp.einsum("...glr,...grm->...glm", c, bq_pk))
    group_weights, mixed = _attend(group_scores, c[..., 0, :, :], valid_edges, num_edge_heads,
                                   scale, attention)
    hidden = (jnp.einsum("...glm,...gmc->...glc", group_weights, per_target(pv))
              + sum(mixed[..., s, None] * (tv[..., None, :] if s == 0 else ev[s - 1, :, None, :])
                    for s in range(mixed.shape[-1])))                           # (..., N, G, L, w)
    return jnp.swapaxes(hidden, -3, -2)


def _active_heads(controls: Controls, num_groups: int) -> jax.Array:
    """(G, 1) 1 for the head slots h < n in use."""
    return (jnp.arange(num_groups) < controls.num_edge_heads).astype(jnp.float32)[:, None]


def sample_edges(edge_probs: jax.Array, noise: jax.Array, controls: Controls, *,
                 hard: bool) -> tuple[jax.Array, jax.Array]:
    """Gumbel-softmax samples of every active head: edge_probs and noise (..., N, G, N+1).

    Returns the sampled edges (..., N, G, N+1) (inactive head slots zero) and the sampled
    adjacency (..., N, N+1) = their sum over heads.
    """
    sampled = gumbel_softmax(jnp.log(edge_probs + EPS), noise, controls.tau, hard)
    sampled = sampled * _active_heads(controls, edge_probs.shape[-2])
    return sampled, sampled.sum(axis=-2)
