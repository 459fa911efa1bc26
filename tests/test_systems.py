"""Feedback-linearizable systems: the FL identity, coordinate changes, discretization, argument checks."""
import numpy as np
import pytest

import flnotes as fl


def _fd_zdot(system, z, v, h=1e-6):
    """d/dt to_z(x) along the true plant with u = Phi(z, v), by a central difference."""
    x = np.asarray(system.to_x(z), float)
    f = np.asarray(system.f(x, system.Phi(z, v)), float)
    return (np.asarray(system.to_z(x + h * f)) - np.asarray(system.to_z(x - h * f))) / (2 * h)


def _two_chains():
    """Chains of integrators of orders 2 and 1 (two inputs), Phi = v."""
    return fl.integrators((2, 1), lo=[-2.0] * 3 + [-1.0] * 2, hi=[2.0] * 3 + [1.0] * 2, u_max=[1.0, 0.5])


SYSTEMS = [fl.msd, fl.quad1d, _two_chains]


@pytest.mark.parametrize("make", SYSTEMS)
def test_feedback_linearization_identity(make):
    """u = Phi(z, v) on the true plant gives z' = A z + B v (eq. linearizedDyna) at random points."""
    system = make()
    X = np.random.default_rng(0).uniform(system.lo, system.hi, (200, system.n_in))
    for z, v in zip(*system.split(X)):
        np.testing.assert_allclose(_fd_zdot(system, z, v), system.A @ z + system.B @ v, atol=1e-6, rtol=0)
        np.testing.assert_allclose(system.linearized_rhs(z, v), system.A @ z + system.B @ v)


@pytest.mark.parametrize("make", SYSTEMS)
def test_to_x_to_z_round_trip(make):
    system = make()
    Z = np.random.default_rng(1).uniform(system.lo[: system.n_z], system.hi[: system.n_z], (100, system.n_z))
    for z in Z:
        np.testing.assert_allclose(system.to_z(system.to_x(z)), z, atol=1e-12)


def test_quad1d_phi_matches_paper_formula_and_singularity():
    q = fl.quad1d()
    G, g, tau = q.params["Gamma"], q.params["gamma"], q.params["tau"]
    X = np.random.default_rng(2).uniform(q.lo, q.hi, (500, 4))
    z, v = q.split(X)
    zeta = (z[:, 2] + g * z[:, 1]) / G
    expected = tau * (v[:, 0] + g * z[:, 2]) / (G * np.sqrt(1 - zeta**2)) + np.arcsin(zeta)
    np.testing.assert_allclose(q.Phi(z, v)[:, 0], expected, rtol=1e-12)
    np.testing.assert_allclose(q.zeta(z), zeta)
    corners = q.grid(2)[:, :3]
    assert np.abs(q.zeta(corners)).max() == pytest.approx(0.65)
    with pytest.raises(ValueError, match="zeta"):
        q.Phi([0.0, 0.0, 10.0], [0.0])  # zeta = 1: singular


def test_integrators_phi_is_v_and_their_plant_is_the_chain():
    """``fl.integrators``: Phi(z, v) = v for each input, the plant is ``A z + B u``, and the input bound is the one given."""
    s = _two_chains()
    assert (s.n_z, s.m) == (3, 2)
    rng = np.random.default_rng(2)
    Z, V = rng.uniform(-2, 2, (50, 3)), rng.uniform(-1, 1, (50, 2))
    np.testing.assert_array_equal(s.Phi(Z, V), V)
    A, B = fl.brunovsky((2, 1))
    np.testing.assert_allclose(s.f(Z[0], V[0]), A @ Z[0] + B @ V[0])
    np.testing.assert_array_equal(s.u_max, [1.0, 0.5])
    with pytest.raises(ValueError):
        fl.integrators(2, lo=[-1.0] * 2, hi=[1.0] * 2, u_max=1.0)  # the box lacks v's interval


def test_msd_phi_is_v_plus_friction_plus_spring():
    m = fl.msd()
    z, v = np.array([0.3, -0.02]), np.array([1.5])
    s = (0.8 + 0.2 * np.exp(-100 * 0.02)) * np.tanh(-0.2) - 0.02
    np.testing.assert_allclose(m.Phi(z, v), [1.5 + s + 0.3])


@pytest.mark.parametrize("orders", [(1,), (2,), (3,), (4,), (2, 2), (1, 3), (2, 1, 1)])
@pytest.mark.parametrize("ts", [0.01, 0.1, 0.7])
def test_discretize_exact_equals_rk4_for_short_chains(orders, ts):
    A, B = fl.brunovsky(orders)
    Ae, Be = fl.discretize(A, B, ts, "exact")
    Ar, Br = fl.discretize(A, B, ts, "rk4")
    np.testing.assert_allclose(Ae, Ar, atol=1e-12)
    np.testing.assert_allclose(Be, Br, atol=1e-12)


def test_discretize_differs_beyond_four_integrators_and_is_exact_zoh():
    A, B = fl.brunovsky([5])
    Ae, Be = fl.discretize(A, B, 0.5, "exact")
    Ar, Br = fl.discretize(A, B, 0.5, "rk4")
    np.testing.assert_allclose(Ae, Ar, atol=1e-12)  # RK4's A_d keeps (hA)^4 / 4!, all a 5-chain has
    assert abs(Be[0, 0] - Br[0, 0]) == pytest.approx(0.5**5 / 120)  # B_d misses h^5 A^4 B / 5!
    # exact ZOH of a 5-chain: A_d[0, 4] = h^4 / 4!, B_d[0] = h^5 / 5!
    assert Ae[0, 4] == pytest.approx(0.5**4 / 24)
    assert Be[0, 0] == pytest.approx(0.5**5 / 120)
    with pytest.raises(ValueError, match="ts"):
        fl.discretize(A, B, 0.0)
    with pytest.raises(ValueError, match="method"):
        fl.discretize(A, B, 0.1, "euler")


@pytest.mark.parametrize("orders,n_z,m", [((2,), 2, 1), ((3,), 3, 1), ((2, 2), 4, 2)])
def test_brunovsky_shapes(orders, n_z, m):
    A, B = fl.brunovsky(orders)
    assert A.shape == (n_z, n_z) and B.shape == (n_z, m)
    assert np.allclose(np.linalg.matrix_power(A, max(orders)), 0)  # nilpotent chains
    assert np.linalg.matrix_rank(np.hstack([np.linalg.matrix_power(A, k) @ B for k in range(n_z)])) == n_z
    with pytest.raises(ValueError, match="orders"):
        fl.brunovsky([])
    assert np.array_equal(fl.brunovsky(np.array(orders))[0], A)  # numpy integers are integers
    if len(orders) == 1:
        assert np.array_equal(fl.brunovsky(np.array(orders[0]))[0], A)  # and a 0-d integer array is one


@pytest.mark.parametrize("orders", [2.5, [2.7], np.array([2.9]), True, "2", "21", None, {2}, [[2, 1]], float("nan"),
                                    float("inf"), [2, 0], -1, [[2], [1, 2]], [2, [1, 2]], np.timedelta64(2),
                                    [np.timedelta64(2)], np.array(True), np.array(2.0)])
def test_brunovsky_refuses_orders_that_are_not_positive_integers(orders):
    """No silent truncation (2.5 is not a double integrator) and one message for every wrong kind."""
    with pytest.raises(ValueError, match="orders must be a positive integer"):
        fl.brunovsky(orders)


def test_a_system_owns_its_arrays():
    """The box, the bound and the Brunovsky pair are copied: editing the caller's arrays, or one system's,
    changes no other system."""
    lo, hi, u_max = np.array([-1.0, -1.0, -1.0]), np.array([1.0, 1.0, 1.0]), np.array([1.0])
    s1, s2 = fl.integrators(2, lo, hi, u_max), fl.integrators(2, lo, hi, u_max)
    lo[2], u_max[0] = 5.0, -3.0
    s1.hi[0] = 100.0
    assert np.array_equal(s1.lo, [-1, -1, -1]) and np.array_equal(s2.hi, [1, 1, 1])
    assert np.array_equal(s1.u_max, [1.0]) and np.array_equal(s2.u_max, [1.0])
    A, B = fl.brunovsky(2)
    s3 = fl.FLSystem("di", A, B, phi=lambda z, v: v, lo=[-1] * 3, hi=[1] * 3, u_max=1.0, f=lambda x, u: A @ x + B @ u,
                     to_z=lambda x: x, to_x=lambda z: z)
    A[0, 1] = 7.0
    assert s3.A[0, 1] == 1.0


def test_a_box_without_width_or_a_name_that_is_no_string_is_refused():
    with pytest.raises(ValueError, match="positive width"):
        fl.integrators(2, lo=[-1.0, -1.0, 0.0], hi=[1.0, 1.0, 0.0], u_max=1.0)
    with pytest.raises(TypeError, match="name must be a string"):
        fl.integrators(2, lo=[-1.0] * 3, hi=[1.0] * 3, u_max=1.0, name=None)


def test_integrators_carry_phi_as_an_interval_function():
    """certify_error needs no extra argument: the exactly-v network has error 0, a network off by a known amount
    has that error, within the bracket."""
    s = fl.integrators(1, [-1.0, -1.0], [1.0, 1.0], 1.0)
    exact = fl.ReLUNet([np.array([[0.0, 1.0], [0.0, -1.0]]), np.array([[1.0, -1.0]])], [np.zeros(2), np.zeros(1)])
    assert fl.certify_error(s, exact, atol=1e-9).upper[0] <= 1e-9
    off = fl.ReLUNet([np.array([[0.0, 1.0], [0.0, -1.0]]), np.array([[1.0, -1.0]])], [np.zeros(2), np.array([0.25])])
    br = fl.certify_error(s, off, atol=1e-9)
    assert br.lower[0] - 1e-9 <= 0.25 <= br.upper[0] + 1e-9


def _two_double_integrators():
    A, B = fl.brunovsky([2, 2])

    def phi(z, v):
        return v + np.sin(z[:, [0, 2]])

    def f(x, u):  # x1'' = u1 - sin(x1), x3'' = u2 - sin(x3)
        return np.array([x[1], u[0] - np.sin(x[0]), x[3], u[1] - np.sin(x[2])])

    return fl.FLSystem(name="2xDI", A=A, B=B, phi=phi, lo=[-1, -1, -2, -2, -3, -3], hi=[1, 1, 2, 2, 3, 3],
                       u_max=[4.0, 4.0], f=f, to_z=lambda x: np.asarray(x, float), to_x=lambda z: np.asarray(z, float))


def test_user_defined_multi_input_system():
    s = _two_double_integrators()
    assert (s.n_z, s.m, s.n_in) == (4, 2, 6)
    assert s.input_names == ("v1", "v2")
    z, v = np.array([0.1, 0.2, -0.3, 0.4]), np.array([1.0, -1.0])
    np.testing.assert_allclose(s.Phi(z, v), v + np.sin([0.1, -0.3]))
    Z, V = np.tile(z, (5, 1)), np.tile(v, (5, 1))
    assert s.Phi(Z, V).shape == (5, 2)
    X = s.stack(Z, V)
    assert X.shape == (5, 6)
    np.testing.assert_allclose(np.hstack(s.split(X)), X)
    np.testing.assert_allclose(s.phi_stacked(X), s.Phi(Z, V))
    G = s.grid(3)
    assert G.shape == (3**6, 6)
    np.testing.assert_allclose(G.min(0), s.lo)
    np.testing.assert_allclose(G.max(0), s.hi)
    assert s.in_domain(G[:, :4], G[:, 4:]).all()
    np.testing.assert_allclose(_fd_zdot(s, z, v), s.A @ z + s.B @ v, atol=1e-6)


def test_bad_arguments_name_the_argument():
    m = fl.msd()
    A2, B2 = fl.brunovsky([2])
    with pytest.raises(ValueError, match="z must have shape"):
        m.Phi(np.zeros(3), [0.0])
    with pytest.raises(ValueError, match="v must have shape"):
        m.Phi(np.zeros((4, 2)), np.zeros((4, 2)))
    with pytest.raises(ValueError, match="same number of points"):
        m.Phi(np.zeros((4, 2)), np.zeros((3, 1)))
    with pytest.raises(ValueError, match="z contains NaN"):
        m.Phi([np.nan, 0.0], [0.0])
    with pytest.raises(ValueError, match="v contains NaN"):
        m.Phi([0.0, 0.0], [np.nan])
    with pytest.raises(ValueError, match=r"z_box must be a finite number > 0 \(the half-width of the state box\)"):
        fl.msd(z_box=-2.0)
    with pytest.raises(ValueError, match="u_max must be a finite number > 0"):
        fl.msd(u_max=0.0)
    with pytest.raises(ValueError, match="u_max must be a finite number > 0"):
        fl.quad1d(u_max=-0.1)
    with pytest.raises(ValueError, match="u_max must be positive"):  # the system's own check of the vector
        fl.FLSystem(name="bad", A=A2, B=B2, phi=None, lo=[0, 0, 0], hi=[1, 1, 1], u_max=[0.0], f=None, to_z=None,
                    to_x=None)
    with pytest.raises(ValueError, match="X must have shape"):
        m.split(np.zeros((2, 4)))
    A, B = fl.brunovsky([2])
    with pytest.raises(ValueError, match="B must have"):
        fl.FLSystem(name="bad", A=A, B=np.ones((3, 1)), phi=None, lo=[0, 0, 0], hi=[1, 1, 1], u_max=[1.0],
                    f=None, to_z=None, to_x=None)


def test_check_domain():
    m = fl.msd()
    m.check_domain([0.0, 4.9])
    m.check_domain([0.0, 4.9], [9.0])
    assert m.in_domain(np.array([[0.0, 0.0], [0.0, 6.0]])).tolist() == [True, False]
    with pytest.raises(ValueError, match=r"z = \[0. 6.\] is outside"):
        m.check_domain([0.0, 6.0])
    with pytest.raises(ValueError, match="outside the network's trained domain"):
        m.check_domain([0.0, 0.0], [11.0], what="(z, v)")
    with pytest.raises(ValueError, match=r"\(z, v\) = "):
        m.check_domain([0.0, 0.0], [11.0], what="(z, v)")


def test_affine_v_interval_is_the_closed_form_and_drawn_exactly():
    """eq. (1.10) for the MSD; the feasible-set figure draws these edges, not a gridded level set."""
    import matplotlib
    matplotlib.use("Agg")
    import flnotes.plots  # noqa: F401  (registers fl.plots)
    msd = fl.msd()
    z = np.random.default_rng(0).uniform(msd.lo[:2], msd.hi[:2], (50, 2))
    lo, hi = fl.plots.affine_v_interval(msd, z)
    shift = fl.systems.stribeck(z[:, 1]) + z[:, 0]
    assert np.allclose(lo, -5 - shift) and np.allclose(hi, 5 - shift)
    quad = fl.quad1d()
    zq = np.random.default_rng(1).uniform(quad.lo[:3], quad.hi[:3], (50, 3))
    lo, hi = fl.plots.affine_v_interval(quad, zq)
    for end in (lo, hi):
        assert np.allclose(np.abs(quad.Phi(zq, end[:, None])), quad.u_max)
    assert np.all(hi - lo > 0)
    fig = fl.plots.plot_feasible_set(msd, axis=1, z_fixed=[0.0, 0.0], v_lim=(-20, 20))
    edges = [ln.get_data() for ln in fig.axes[0].lines if len(ln.get_xdata()) > 2]  # not the dashed box limits
    assert len(edges) == 2
    zs, upper = np.asarray(edges[1][0], float), np.asarray(edges[1][1], float)
    assert np.allclose(upper, 5 - fl.systems.stribeck(zs))
    with pytest.raises(ValueError, match="z must have shape"):
        fl.plots.affine_v_interval(msd, np.zeros(2))
