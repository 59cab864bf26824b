"""Per-indenter table of the contact mechanics on simulated recordings (docs/contact-mechanics.md).

Reads two outputs of `truth_eval` with VERBOSE=1 (exact 3-D and with noise), each recording's
meta.json naming its indenter, and prints one row per indenter: frames whose true contact covers at
least 4 pitch^2 (0.8 mm pitch), the shares of them with the area and the force within 20 % of the
truth, the median centroid and depth errors, and the gross-slip F1 over all frames.

    python train/scripts/contact_family_table.py EXACT.txt NOISY.txt
"""
import json,re,collections,sys,statistics
def kind(rec): return json.load(open(rec+'/meta.json'))['indenter'].get('shape')
pat=re.compile(r'(\S+) f\s+(\d+) area\s+([\d.]+)/\s*([\d.]+) \(\S+\) force ([\d.naN]+)/([\d.naN]+) cone \S+ ratio \S+ depth ([\d.]+)/([\d.]+) cent (\S+) slip\s+(\S+)/(\S+)')
def load(path):
    fam=collections.defaultdict(lambda: dict(a=[],f=[],c=[],d=[],tp=0,fp=0,fn=0))
    for line in open(path):
        m=pat.match(line)
        if not m: continue
        F=fam[kind(m.group(1))]
        ae,at,fe,ft,de,dt=[float(m.group(i)) for i in range(3,9)]
        ce,se,st=m.group(9),m.group(10),m.group(11)
        if at>=4*0.64:
            F['a'].append(ae/at); F['f'].append(fe/ft if ft>0 else float('nan')); F['d'].append(abs(de-dt))
            if ce!='inf': F['c'].append(float(ce))
        g,t=se=='gross_slip',st=='gross_slip'
        F['tp']+=g and t; F['fp']+=g and not t; F['fn']+=t and not g
    return fam
A,B=load(sys.argv[1]),load(sys.argv[2])
w=lambda xs,t: 100*sum(abs(x-1)<=t for x in xs)/len(xs)
f1=lambda F: f"{2*F['tp']/(2*F['tp']+F['fp']+F['fn']):.2f}" if F['tp']+F['fp']+F['fn'] else "–"
print("| indenter | frames | area within 20 % | force within 20 % | centroid error, median | depth error, median | gross-slip F1 |")
print("|---|---|---|---|---|---|---|")
for k in sorted(A):
    a,b=A[k],B[k]
    if not a['a']: continue
    print(f"| {k.replace('_',' ')} | {len(a['a'])} | {w(a['a'],.2):.0f} / {w(b['a'],.2):.0f} % | {w(a['f'],.2):.0f} / {w(b['f'],.2):.0f} % | {statistics.median(a['c']):.2f} / {statistics.median(b['c']):.2f} mm | {statistics.median(a['d']):.3f} / {statistics.median(b['d']):.3f} mm | {f1(a)} / {f1(b)} |")
def allf(F):
    a=[x for v in F.values() for x in v['a']]; f=[x for v in F.values() for x in v['f']]
    return w(a,.2), w(f,.2)
(ea, ef), (na, nf) = allf(A), allf(B)
print(f"all: area within 20 % {ea:.0f} / {na:.0f} %, force within 20 % {ef:.0f} / {nf:.0f} %")
