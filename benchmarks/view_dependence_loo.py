"""Leave-one-out study: how well per-pixel predictors built from the other photos reproduce each photo
of a posed capture on its mesh (the question behind the view-dependent radiance model, fit/models.py).

    python benchmarks/view_dependence_loo.py POSED_CAPTURE MESH

For every registered photo in turn: its foreground pixels' surface points (the mesh's depth map), the
other photos sampled there (visible by depth, inside their masks, bilinear), and predictions of the
held-out pixel: the plain average (what texture bakers store), cos-weighted averages, view-weighted
averages exp(s (cos angle - 1)) (view-dependent texture mapping), and per-pixel polynomials of the local
view direction (linear, biquadratic: the view_radiance model) with a ridge prior, in proportion to the
sample count (positive lam) or absolute (negative lam). Prints PSNR per photo and pooled. numpy only, no fit.
"""
import sys

import numpy as np
import warp as wp
wp.config.quiet = True
from texstream.capture.capture_json import read_capture
from texstream.capture.imageio import read_image, read_mask
from texstream.geometry.mesh_io import load_mesh
from texstream.geometry.visibility import Visibility
root = sys.argv[1]; meshp = sys.argv[2]
cap = read_capture(root)
mesh = load_mesh(meshp)
vis = Visibility(mesh, 'cpu')
fr = cap.frames
imgs = [read_image(cap.image_path(f), channels=3) / f.exposure for f in fr]
masks = [read_mask(cap.mask_path(f), imgs[0].shape[:2]) for f in fr]
deps, faces = zip(*[vis.render(f) for f in fr])
V = np.asarray(mesh.vertices, np.float64); F = np.asarray(mesh.faces)
fn = np.cross(V[F[:,1]]-V[F[:,0]], V[F[:,2]]-V[F[:,0]]); fn /= np.linalg.norm(fn, axis=1, keepdims=True)+1e-12
def bil(img, x, y):
    x0 = np.floor(x).astype(int); y0 = np.floor(y).astype(int); fx = x-x0; fy = y-y0
    H, W = img.shape[:2]
    x0 = np.clip(x0,0,W-2); y0=np.clip(y0,0,H-2)
    return ((1-fy)*((1-fx)*img[y0,x0].T + fx*img[y0,x0+1].T) + fy*((1-fx)*img[y0+1,x0].T+fx*img[y0+1,x0+1].T)).T
res = {}
for h in range(len(fr)):
    f = fr[h]; K = f.intrinsics
    d = deps[h]; m = np.isfinite(d) & masks[h]
    jj, ii = np.nonzero(m)
    z = d[jj, ii]
    xc = np.stack([(ii+0.5-K.cx)/K.fx*z, (jj+0.5-K.cy)/K.fy*z, z], 1)
    P = (xc - f.t.reshape(3)) @ f.R  # world = R^T (xc - t)
    N = fn[faces[h][jj, ii]]
    vh = f.center - P; vh /= np.linalg.norm(vh, axis=1, keepdims=True)
    N = np.where((np.sum(N*vh,1) < 0)[:,None], -N, N)
    samples, ws = [], []
    for k in range(len(fr)):
        if k == h: continue
        g = fr[k]; Kk = g.intrinsics
        pc = P @ g.R.T + g.t.reshape(3)
        x = Kk.fx*pc[:,0]/pc[:,2] + Kk.cx - 0.5; y = Kk.fy*pc[:,1]/pc[:,2] + Kk.cy - 0.5
        ok = (pc[:,2] > 0) & (x >= 0) & (y >= 0) & (x < Kk.width-1) & (y < Kk.height-1)
        xi = np.clip(np.round(x).astype(int),0,Kk.width-1); yi = np.clip(np.round(y).astype(int),0,Kk.height-1)
        ok &= pc[:,2] <= deps[k][yi, xi]*(1+5e-3)
        ok &= masks[k][yi, xi]
        vk = g.center - P; vk /= np.linalg.norm(vk, axis=1, keepdims=True)
        cosv = np.sum(N*vk, 1); ok &= cosv > 0.05
        s = bil(imgs[k], x, y)
        samples.append((ok, s, cosv, np.sum(vk*vh,1)))
    y_true = imgs[h][jj, ii]
    def pred(wfun):
        num = np.zeros_like(y_true); den = np.zeros(len(P))
        for ok, s, cosv, cosang in samples:
            w = wfun(cosv, cosang) * ok
            num += w[:,None]*s; den += w
        have = den > 0
        return num/np.maximum(den,1e-12)[:,None], have
    out = {}
    for name, wf in [('avg', lambda c,a: np.ones_like(c)), ('cos', lambda c,a: c), ('cos2', lambda c,a: c**2),
                     ('vd8', lambda c,a: np.exp(8*(a-1))), ('vd20', lambda c,a: np.exp(20*(a-1))), ('vd50', lambda c,a: np.exp(50*(a-1))),
                     ('vd20cos', lambda c,a: c*np.exp(20*(a-1)))]:
        p, have = pred(wf)
        out[name] = p
    have_all = pred(lambda c,a: np.ones_like(c))[1]
    row = {}
    for name, p in out.items():
        e = ((p - y_true)**2)[have_all]
        row[name] = (e.sum(), e.size)
    res[f.name] = row
names = list(next(iter(res.values())).keys())
print('view', *names)
for v, row in res.items():
    print(v, *[f"{10*np.log10(row[n][1]/row[n][0]):.2f}" for n in names])
print('POOLED', *[f"{10*np.log10(sum(r[n][1] for r in res.values())/sum(r[n][0] for r in res.values())):.2f}" for n in names])

# --- per-pixel view-dependent polynomial fits (ridge toward constant), leave-one-out
def lin_eval(order, lam):
    tot = [0.0, 0]
    per = {}
    for h in range(len(fr)):
        f = fr[h]; K = f.intrinsics
        d = deps[h]; m = np.isfinite(d) & masks[h]
        jj, ii = np.nonzero(m); z = d[jj, ii]
        xc = np.stack([(ii+0.5-K.cx)/K.fx*z, (jj+0.5-K.cy)/K.fy*z, z], 1)
        P = (xc - f.t.reshape(3)) @ f.R
        N = fn[faces[h][jj, ii]]
        vh = f.center - P; vh /= np.linalg.norm(vh, axis=1, keepdims=True)
        N = np.where((np.sum(N*vh,1) < 0)[:,None], -N, N)
        a = np.where(np.abs(N[:,0:1]) < 0.9, np.array([[1.,0,0]]), np.array([[0,1.,0]]))
        T = np.cross(N, a); T /= np.linalg.norm(T,axis=1,keepdims=True); B = np.cross(N, T)
        def feats(v):
            x = np.sum(v*T,1); y = np.sum(v*B,1)
            fs = [np.ones_like(x), x, y]
            if order >= 2: fs += [x*x, x*y, y*y]
            return np.stack(fs, 1)
        nf = 3 if order == 1 else 6
        A = np.zeros((len(P), nf, nf)); bvec = np.zeros((len(P), nf, 3)); cnt = np.zeros(len(P))
        for k in range(len(fr)):
            if k == h: continue
            g = fr[k]; Kk = g.intrinsics
            pc = P @ g.R.T + g.t.reshape(3)
            x = Kk.fx*pc[:,0]/pc[:,2] + Kk.cx - 0.5; y = Kk.fy*pc[:,1]/pc[:,2] + Kk.cy - 0.5
            ok = (pc[:,2] > 0) & (x >= 0) & (y >= 0) & (x < Kk.width-1) & (y < Kk.height-1)
            xi = np.clip(np.round(x).astype(int),0,Kk.width-1); yi = np.clip(np.round(y).astype(int),0,Kk.height-1)
            ok &= pc[:,2] <= deps[k][yi, xi]*(1+5e-3); ok &= masks[k][yi, xi]
            vk = g.center - P; vk /= np.linalg.norm(vk, axis=1, keepdims=True)
            ok &= np.sum(N*vk, 1) > 0.05
            s = bil(imgs[k], x, y); phi = feats(vk) * ok[:,None]
            A += phi[:,:,None]*phi[:,None,:]; bvec += phi[:,:,None]*s[:,None,:]; cnt += ok
        reg = lam*np.eye(nf); reg[0,0] = 1e-9
        A = A + (reg[None] * np.maximum(cnt, 1)[:, None, None] if lam > 0 else -reg[None])
        c = np.linalg.solve(A, bvec)
        p = np.einsum('nf,nfc->nc', feats(vh), c)
        have = cnt > 0
        e = ((p - imgs[h][jj, ii])**2)[have]
        per[f.name] = 10*np.log10(e.size/e.sum())
        tot[0] += e.sum(); tot[1] += e.size
    return 10*np.log10(tot[1]/tot[0]), per
for order, lam in [(1, 0.1), (2, 0.1), (2, -0.5)]:
    pooled, per = lin_eval(order, lam)
    print('poly', order, lam, f"pooled {pooled:.2f}", 'SR0010', f"{per.get('templeSR0010', float('nan')):.2f}")
