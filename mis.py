"""Experiment: label core components that a neighbour's flooding takes when their markers go."""
import sys, numpy as np, time
from scipy import ndimage
from BoneWatertightLib.stages import ownership as O
d = np.load(sys.argv[1]); ct, labels, n, spacing = d['ct'], d['labels'], int(d['n']), float(d['spacing'])
kw = {k[3:]: float(d[k]) for k in d.files if k.startswith('kw_')}
h0, ht, soft, contrast, coarseness, band_mm = kw['h0'], kw['ht'], kw['soft'], kw['contrast'], kw['coarseness'], kw['band_mm']
r_core = max(O.CORE_MIN_MM, coarseness); r_contact = max(O.CONTACT_MIN_MM, coarseness)
t_low = soft + O.LABEL_LEVEL_FRACTION * (ht - soft)
t0 = time.time()
seg = O._label_parts(ct, labels, n, spacing, r_core=r_core, r_contact=r_contact, band_mm=band_mm, t_low=t_low)
fg, strong = O._bone_foreground(ct, labels > 0, seg.cores, h0=h0, ht=ht, t_low=t_low, theta_max=kw['theta_max'])
other = n + 1
quantum = max(O.VALLEY_QUANTUM_MIN_HU, O.VALLEY_QUANTUM_FRACTION * contrast)
radius = 0.5 * O.VALLEY_GAP_MM + spacing
levels = np.minimum(np.floor(np.clip(O.valley_map(ct, spacing, radius), 0, None) / quantum), 255).astype(np.uint8)
seen = ~strong & (levels >= O.SEEN_VALLEY_QUANTA)
markers, n_pieces, dropped = O._markers(fg, strong, labels, seg, other, spacing, seen=seen)
print('setup', round(time.time() - t0, 1), 's; grid', ct.shape, 'spacing', spacing, 'n', n)
MIN_ML = float(sys.argv[2]) if len(sys.argv) > 2 else 0.05
cands = []
trial = markers.copy()
for a, (sl, reg) in seg.regions.items():
    core = seg.cores[sl] == a
    cl, nc = ndimage.label(core, structure=O.SIX)
    if nc < 2: continue
    sz = np.bincount(cl.ravel()); sz[0] = 0; big = int(np.argmax(sz))
    others_reg = np.zeros(core.shape, bool)
    for b, (slb, regb) in seg.regions.items():
        if b == a: continue
        # regb on slb: intersect with sl
        lo = [max(s1.start, s2.start) for s1, s2 in zip(sl, slb)]; hi = [min(s1.stop, s2.stop) for s1, s2 in zip(sl, slb)]
        if any(h <= l for l, h in zip(lo, hi)): continue
        others_reg[tuple(slice(l - s.start, h - s.start) for l, h, s in zip(lo, hi, sl))] |= regb[tuple(slice(l - s.start, h - s.start) for l, h, s in zip(lo, hi, slb))]
    _, idx = ndimage.distance_transform_edt(~core, return_indices=True)
    nearest = cl[tuple(idx)]
    lab_a = labels[sl] == a
    for c in range(1, nc + 1):
        if c == big: continue
        ml = sz[c] * spacing ** 3 / 1000
        m = cl == c
        inside = float(others_reg[m].mean())
        if ml < MIN_ML: continue
        terr = lab_a & (nearest == c)
        cands.append((a, c, ml, inside, sl, m, terr, sz[big] * spacing ** 3 / 1000))
        if inside >= 0.5:
            t = trial[sl]; t[terr & (t == a)] = 0
t1 = time.time()
ws = O.flood_from_markers(trial, levels, fg)
print('trial flood', round(time.time() - t1, 2), 's;', len(cands), 'candidates')
for a, c, ml, inside, sl, m, terr, bigml in cands:
    own = np.bincount(ws[sl][m], minlength=other + n_pieces + 1)
    tot = m.sum()
    top = {int(k): round(v / tot, 2) for k, v in enumerate(own) if v / tot >= 0.05}
    print(f'label {a} comp {c}: core {ml:.2f} ml (largest {bigml:.2f}), in others regions {inside:.2f}, territory {terr.sum()*spacing**3/1000:.2f} ml -> {top if inside >= 0.5 else "-"}')
