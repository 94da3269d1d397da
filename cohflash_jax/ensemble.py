"""emcee's ensemble sampler, its step computed for many independent targets at once.

`DEMove`, `SnookerMove` and `EnsembleSampler` are emcee's own moves and sampler, with each
step's per-walker Python replaced by array operations that draw the same random numbers.
`LockstepEnsembles` steps many targets (the pixels of a posterior run) together: each keeps
its own `RandomState` and draws from it what emcee would draw, in emcee's order, so each chain
is the one emcee's sampler walks for that target alone (tested against emcee's stock sampler);
the Python of a step and the log-probability's NumPy calls are paid once for all targets."""

from __future__ import annotations

import emcee
import numpy as np
from emcee.ensemble import walkers_independent


class AcceptanceInOneDraw:
    """For emcee's red-blue moves: each sub-ensemble's Metropolis test in one draw. emcee's
    `RedBlueMove.propose` compares each walker's log-ratio with log U in a Python loop, one
    `random.rand()` a walker; `rand(k)` gives the same k numbers from NumPy's legacy
    `RandomState`, so the chains are emcee's own, step for step (tested), in less of a step's time.

    A move that also defines `proposals` (k walkers of n ensembles at once, one random state
    each) can be stepped by `LockstepEnsembles`."""

    def propose(self, model, state):
        nwalkers, ndim = state.coords.shape
        if nwalkers < 2 * ndim and not self.live_dangerously:
            raise RuntimeError(
                "It is unadvisable to use a red-blue move with fewer walkers than twice the number of dimensions."
            )
        self.setup(state.coords)
        accepted = np.zeros(nwalkers, dtype=bool)
        inds = np.arange(nwalkers) % self.nsplits
        if self.randomize_split:
            model.random.shuffle(inds)
        for split in range(self.nsplits):
            mine = inds == split
            sets = [state.coords[inds == j] for j in range(self.nsplits)]
            proposal, factors = self.get_proposal(sets[split], sets[:split] + sets[split + 1 :], model.random)
            log_probs, blobs = model.compute_log_prob_fn(proposal)
            log_ratio = factors + log_probs - state.log_prob[mine]
            accepted[mine] = log_ratio > np.log(model.random.rand(int(mine.sum())))
            state = self.update(state, emcee.State(proposal, log_prob=log_probs, blobs=blobs), accepted, mine)
        return state, accepted


class DEMove(AcceptanceInOneDraw, emcee.moves.DEMove):
    """emcee's differential-evolution move, its acceptance drawn at once (`AcceptanceInOneDraw`)."""

    def proposals(self, s, c, randoms):
        """emcee's `get_proposal` for n ensembles at once: the k walkers `s` (n, k, d) and the
        complementary sub-ensembles `c` (a list of (n, m, d)), each ensemble drawing from its
        own random state in `randoms` the pair indices and the γ jitter emcee draws."""
        c = np.concatenate(c, axis=1)
        n, k, _ = s.shape
        rows, cols = np.tril_indices(c.shape[1], -1)  # emcee's non-diagonal pairs, in its order
        pairs = np.column_stack([np.concatenate([rows, cols]), np.concatenate([cols, rows])])
        # `random.choice(len(pairs), size=k)`'s draws, without its checks of its arguments
        draws = [(random.randint(0, pairs.shape[0], size=k), random.randn(k, 1)) for random in randoms]
        chosen = pairs[np.stack([index for index, _ in draws])]  # (n, k, 2)
        rows = np.arange(n)[:, None]
        gamma = self.g0 * (1 + self.sigma * np.stack([jitter for _, jitter in draws]))  # (n, k, 1)
        return s + gamma * (c[rows, chosen[..., 1]] - c[rows, chosen[..., 0]]), np.zeros((n, k), dtype=np.float64)


class SnookerMove(AcceptanceInOneDraw, emcee.moves.DESnookerMove):
    """emcee's differential-evolution snooker move (Ter Braak & Vrugt 2008), the same proposal
    drawn for all walkers of a sub-ensemble at once. emcee's own draws them walker by walker in
    Python, a fifth of a pixel's sampling time (docs/performance.md). Each walker takes one
    walker of each complementary sub-ensemble in a random order: z, then z₁ and z₂; it moves
    along u = (x − z)/√|x − z| by γ·u·(z₁ − z₂), with the snooker's Metropolis factor
    ½(d − 1)·log(|x′ − z|/|x − z|). Its random draws differ from emcee's, not their law (tested);
    its acceptance is drawn at once (`AcceptanceInOneDraw`)."""

    def get_proposal(self, s, c, random):
        q, factors = self.proposals(s[None], [cj[None] for cj in c], [random])
        return q[0], factors[0]

    def proposals(self, s, c, randoms):
        """The proposal of n ensembles at once (`DEMove.proposals`), each drawing from its own
        random state what `get_proposal` draws for it alone."""
        _, walkers, ndim = s.shape
        draws = [
            ([random.randint(cj.shape[1], size=walkers) for cj in c[:3]], random.random_sample((walkers, 3)))
            for random in randoms
        ]
        rows = np.arange(len(randoms))[:, None]
        # (n, walkers, 3, d): the chosen walker of each complementary sub-ensemble
        others = np.stack([cj[rows, np.stack([picks[j] for picks, _ in draws])] for j, cj in enumerate(c[:3])], axis=2)
        order = np.argsort(np.stack([u for _, u in draws]), axis=-1)  # emcee's shuffle of the three
        z, z1, z2 = np.moveaxis(others[rows[..., None], np.arange(walkers)[:, None], order], 2, 0)
        delta = s - z
        norm = np.linalg.norm(delta, axis=-1)
        u = delta / np.sqrt(norm)[..., None]
        q = s + u * self.gammas * np.sum(u * (z1 - z2), axis=-1, keepdims=True)
        metropolis = np.log(np.linalg.norm(q - z, axis=-1)) - np.log(norm)
        return q, 0.5 * (ndim - 1.0) * metropolis


class EnsembleSampler(emcee.EnsembleSampler):
    """emcee's sampler taking a vectorised log-probability's array as it is: emcee's own
    `compute_log_prob` makes a Python scalar of each walker's value (looking for blobs), a good
    part of a step where the log-probability itself is a few NumPy operations. The same values;
    NaN refused as emcee refuses it; non-finite walkers left to emcee's checks and messages."""

    def compute_log_prob(self, coords):
        if not self.vectorize or self.params_are_named or not np.all(np.isfinite(coords)):
            return super().compute_log_prob(coords)
        log_prob = np.asarray(self.log_prob_fn(coords), np.float64)
        if log_prob.shape != (coords.shape[0],):  # blobs, or another shape: emcee sorts it out
            return super().compute_log_prob(coords)
        if np.any(np.isnan(log_prob)):
            raise ValueError("Probability function returned NaN")
        return log_prob, None


class LockstepEnsembles:
    """emcee's `EnsembleSampler` (vectorised, with red-blue `moves` that define `proposals`)
    run for P independent targets at once, stepped together.

    `log_prob(targets, thetas)`: the log-probabilities (n, k) of walkers `thetas` (n, k, d) of
    the n `targets` (indices into the P). Each target is started (`start`: its walkers and its
    `RandomState` seed, as `EnsembleSampler.random_state` would be set) before it is run; a
    target may start while others run.

    Every step of a target draws from its own state, in emcee's order: the move, the split,
    and for each sub-ensemble the proposal and then the acceptance uniforms. So its chain,
    log-probabilities and acceptance are emcee's, to the bit (tested). `run` steps any subset
    of the started targets (those still sampling), as `run_mcmc` would step each."""

    def __init__(self, log_prob, targets: int, walkers: int, ndim: int, moves):
        self.log_prob_fn = log_prob
        self.moves = [move for move, _ in moves]
        weights = np.atleast_1d([weight for _, weight in moves]).astype(float)
        weights /= np.sum(weights)
        self.move_cdf = weights.cumsum() / weights.cumsum()[-1]  # as `RandomState.choice` takes them
        self.randoms: list[np.random.RandomState | None] = [None] * targets
        self.coords = np.full((targets, walkers, ndim), np.nan)
        self.log_prob = np.full((targets, walkers), np.nan)
        self.accepted = np.zeros((targets, walkers))
        self.iteration = np.zeros(targets, dtype=int)
        self._chains: list[np.ndarray | None] = [None] * targets  # each target's stored states

    def start(self, targets, initial, seeds):
        """Start `targets` (n,) from their walkers `initial` (n, W, d), each with its seed: their
        log-probabilities are taken now, as emcee's `run_mcmc` takes a start's."""
        targets = np.atleast_1d(np.asarray(targets, dtype=int))
        for t, seed in zip(targets, np.atleast_1d(seeds)):
            self.randoms[t] = np.random.RandomState(int(seed))
        self.coords[targets] = initial
        self.log_prob[targets] = self._log_prob(targets, self.coords[targets])

    def _log_prob(self, targets, thetas):
        if not np.all(np.isfinite(thetas)):
            raise ValueError("At least one parameter value was infinite or NaN")
        log_prob = np.asarray(self.log_prob_fn(targets, thetas), np.float64)
        if np.any(np.isnan(log_prob)):
            raise ValueError("Probability function returned NaN")
        return log_prob

    def run(self, targets, steps: int):
        """`steps` steps of each of `targets` (an index array), its states stored."""
        targets = np.asarray(targets, dtype=int)
        for t in targets:
            if self.randoms[t] is None:
                raise ValueError(f"target {t} was not started")
            if not walkers_independent(self.coords[t]):
                raise ValueError(
                    "Initial state has a large condition number. Make sure that your walkers are "
                    "linearly independent for the best performance"
                )
        block = np.empty((targets.size, steps) + self.coords.shape[1:])
        for step in range(steps):
            move_of = np.searchsorted(self.move_cdf, [self.randoms[t].random_sample() for t in targets], side="right")
            accepted = np.zeros((targets.size, self.coords.shape[1]), dtype=bool)
            for m, move in enumerate(self.moves):
                group = np.flatnonzero(move_of == m)
                if group.size:
                    accepted[group] = self._propose(move, targets[group])
            self.accepted[targets] += accepted
            block[:, step] = self.coords[targets]
        for i, t in enumerate(targets):  # grown a run at a time, as emcee's backend grows
            self._chains[t] = block[i] if self._chains[t] is None else np.concatenate([self._chains[t], block[i]])
        self.iteration[targets] += steps

    def _propose(self, move, targets):
        """One step of `move` for `targets`: `AcceptanceInOneDraw.propose` for each at once."""
        coords, log_prob = self.coords[targets], self.log_prob[targets]
        n, walkers, ndim = coords.shape
        if walkers < 2 * ndim and not move.live_dangerously:
            raise RuntimeError(
                "It is unadvisable to use a red-blue move with fewer walkers than twice the number of dimensions."
            )
        move.setup(coords[0])
        randoms = [self.randoms[t] for t in targets]
        labels = np.tile(np.arange(walkers) % move.nsplits, (n, 1))
        if move.randomize_split:
            for row, random in zip(labels, randoms):
                random.shuffle(row)
        # each sub-ensemble's walkers in ascending order, as `coords[labels == j]` takes them
        members = np.argsort(labels, axis=1, kind="stable").reshape(n, move.nsplits, -1)
        accepted = np.zeros((n, walkers), dtype=bool)
        rows = np.arange(n)[:, None].repeat(walkers // move.nsplits, axis=1)
        for split in range(move.nsplits):
            sets = [coords[rows, members[:, j]] for j in range(move.nsplits)]
            mine = members[:, split]
            proposal, factors = move.proposals(sets[split], sets[:split] + sets[split + 1 :], randoms)
            new = self._log_prob(targets, proposal)
            log_ratio = factors + new - log_prob[rows, mine]
            ok = log_ratio > np.log(np.stack([random.rand(mine.shape[1]) for random in randoms]))
            moved = (rows[ok], mine[ok])
            coords[moved], log_prob[moved], accepted[moved] = proposal[ok], new[ok], True
        self.coords[targets], self.log_prob[targets] = coords, log_prob
        return accepted

    def chain(self, target: int) -> np.ndarray:
        """Target's stored states (steps, W, d), as emcee's `get_chain()`."""
        chain = self._chains[target]
        return np.empty((0,) + self.coords.shape[1:]) if chain is None else chain

    def acceptance_fraction(self, target: int) -> np.ndarray:
        return self.accepted[target] / float(self.iteration[target])

    def release(self, target: int):
        """Forget a finished target's chain (its memory)."""
        self._chains[target] = None


def integrated_times(chain: np.ndarray, c: float = 5) -> np.ndarray:
    """emcee's `autocorr.integrated_time(chain, tol=0)` of a chain (steps, W, d) → (d,): each
    walker's normalised autocorrelation function (by FFT, zero-padded to twice the next power
    of two), averaged over the walkers, summed to τ within Sokal's window of `c`·τ. The
    walkers' transforms are taken in one call a chain rather than one a walker and
    parameter: the same numbers (tested)."""
    steps, walkers, ndim = chain.shape
    series = np.ascontiguousarray(np.moveaxis(chain, 0, -1))  # (W, d, steps): each series contiguous
    padded = 2 * (1 << max(0, (steps - 1).bit_length()))
    spectrum = np.fft.fft(series - np.mean(series, axis=-1, keepdims=True), n=padded, axis=-1)
    # |spectrum|² row by row, as emcee takes it: NumPy's complex product of a whole array rounds
    # the (zero) imaginary parts otherwise than row by row, and the inverse transform sees them
    power = np.stack([row * np.conjugate(row) for row in spectrum.reshape(-1, padded)]).reshape(spectrum.shape)
    acf = np.fft.ifft(power, axis=-1)[..., :steps].real
    taus = 2.0 * np.cumsum(np.sum(acf / acf[..., :1], axis=0) / walkers, axis=-1) - 1.0  # (d, steps)
    inside = np.arange(steps) < c * taus
    window = np.where(inside.any(axis=-1), np.argmin(inside, axis=-1), steps - 1)
    return taus[np.arange(ndim), window]
