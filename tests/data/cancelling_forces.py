"""Four particles in the plane with the pair potential (r^2 - 1/4)^2: D's y-forces from B and C
cancel, and D sits 1e-16 off the x-axis, so d2H/dyD dxA is 8e-16, below what differences resolve."""
NAME = "cancelling_forces"
Y0 = [0.0, 0.0, 1.0, 1e-16, 1.0, 1.0, 1.0, -1.0, 0.0, 0.1, 0.0, 0.0, 0.0, 0.0, -0.1, 0.0]


def H(y, params):
    kinetic = 0.0
    for i in range(8, 16):
        kinetic += 0.5 * y[i] * y[i]
    potential = 0.0
    for a in range(4):
        for b in range(a + 1, 4):
            dx = y[2 * a] - y[2 * b]
            dy = y[2 * a + 1] - y[2 * b + 1]
            w = dx * dx + dy * dy - 0.25
            potential += w * w
    return kinetic + potential


def grad_H(y, params, out):
    for i in range(8):
        out[i] = 0.0
    for i in range(8, 16):
        out[i] = y[i]
    for a in range(4):
        for b in range(a + 1, 4):
            dx = y[2 * a] - y[2 * b]
            dy = y[2 * a + 1] - y[2 * b + 1]
            f = 4.0 * (dx * dx + dy * dy - 0.25)
            out[2 * a] += f * dx
            out[2 * a + 1] += f * dy
            out[2 * b] -= f * dx
            out[2 * b + 1] -= f * dy


def hess_H(y, params, out):
    for i in range(16):
        for j in range(16):
            out[i, j] = 0.0
    for i in range(8, 16):
        out[i, i] = 1.0
    for a in range(4):
        for b in range(a + 1, 4):
            d = (y[2 * a] - y[2 * b], y[2 * a + 1] - y[2 * b + 1])
            w = 4.0 * (d[0] * d[0] + d[1] * d[1] - 0.25)
            for u in range(2):
                for v in range(2):
                    block = 8.0 * d[u] * d[v] + (w if u == v else 0.0)
                    out[2 * a + u, 2 * a + v] += block
                    out[2 * b + u, 2 * b + v] += block
                    out[2 * a + u, 2 * b + v] -= block
                    out[2 * b + u, 2 * a + v] -= block
