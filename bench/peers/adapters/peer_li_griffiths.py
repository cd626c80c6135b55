"""Li & Griffiths (2004), "Least squares ellipsoid specific fitting", Proc. Geometric
Modeling and Processing, pp. 335-340: a reimplementation from the paper's description
for this benchmark (no PyPI package provides it as a library call). Written independently
of generator/fit/ellipsoid.py and, like the paper, on the readings as they come (no
centring or scaling of the coordinates).

The paper. Quadric a x^2 + b y^2 + c z^2 + 2f yz + 2g xz + 2h xy + 2p x + 2q y + 2r z
+ d = 0, coefficients v = [a b c f g h p q r d]^T, one design column per reading
D_i = [x^2 y^2 z^2 2yz 2xz 2xy 2x 2y 2z 1]^T. With I = a+b+c and J = ab+bc+ca-f^2-g^2-h^2,
k J - I^2 > 0 (k = 4) is sufficient for an ellipsoid; the fit minimises |D^T v|^2 subject
to k J - I^2 = 1, i.e. v^T C v = 1 with C = diag(C1, 0_4x4),

    C1 = [[-1, k/2-1, k/2-1], [k/2-1, -1, k/2-1], [k/2-1, k/2-1, -1]]  (+)  -k I_3,

giving S v = lambda C v with S = D D^T. Splitting v = [v1 (6); v2 (4)]:
v2 = -S22^-1 S21 v1 and C1^-1 (S11 - S12 S22^-1 S21) v1 = lambda v1; the solution is the
eigenvector of the (unique) positive eigenvalue. (For data not satisfying the k = 4
condition the paper searches larger k by bisection; that branch is not reimplemented:
when no positive eigenvalue gives an ellipsoid this raises, and the table says so.)

Calibration from the quadric, as users of the method write it (not in the paper):
A = [[a,h,g],[h,b,f],[g,f,c]], n = [p,q,r]: centre = -A^-1 n and, for a unit sphere,
matrix = A^(1/2) / sqrt(n^T A^-1 n - d) (symmetric square root).
"""

import numpy as np

from _protocol import run

K = 4.0


def li_griffiths_quadric(x):
    """Quadric coefficients v (10,) of the ellipsoid-specific least-squares fit."""
    X, Y, Z = x[:, 0], x[:, 1], x[:, 2]
    D = np.array([X * X, Y * Y, Z * Z, 2 * Y * Z, 2 * X * Z, 2 * X * Y,
                  2 * X, 2 * Y, 2 * Z, np.ones_like(X)])
    S = D @ D.T
    S11, S12, S22 = S[:6, :6], S[:6, 6:], S[6:, 6:]
    C1 = np.zeros((6, 6))
    C1[:3, :3] = K / 2 - 1
    np.fill_diagonal(C1[:3, :3], -1.0)
    C1[3:, 3:] = -K * np.eye(3)
    T = np.linalg.solve(S22, S12.T)                 # S22^-1 S21
    E = np.linalg.solve(C1, S11 - S12 @ T)
    w, V = np.linalg.eig(E)
    w, V = np.real(w), np.real(V)
    positive = np.nonzero(w > 0)[0]
    if len(positive) == 0:
        raise ValueError("no positive eigenvalue: the data do not satisfy the k = 4 "
                         "ellipsoid condition")
    v1 = V[:, positive[np.argmax(w[positive])]]
    v2 = -T @ v1
    return np.concatenate([v1, v2])


def calibration_from_quadric(v):
    a, b, c, f, g, h, p, q, r, d = v
    A = np.array([[a, h, g], [h, b, f], [g, f, c]])
    n = np.array([p, q, r])
    if np.trace(A) < 0:                                # eigenvector sign is arbitrary
        A, n, d = -A, -n, -d
    evals, evecs = np.linalg.eigh(A)
    if evals[0] <= 0:
        raise ValueError(f"fitted quadric is not an ellipsoid (eigenvalues {evals})")
    centre = -np.linalg.solve(A, n)
    scale = float(n @ np.linalg.solve(A, n) - d)
    if scale <= 0:
        raise ValueError("fitted quadric is imaginary (n^T A^-1 n - d <= 0)")
    matrix = (evecs * np.sqrt(evals)) @ evecs.T / np.sqrt(scale)
    return centre, matrix


def fit(x):
    return calibration_from_quadric(li_griffiths_quadric(np.asarray(x, float)))


if __name__ == "__main__":
    raise SystemExit(run("Li & Griffiths 2004", None, fit))
