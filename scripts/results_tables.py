"""Print the numeric parts of docs/results.md from an evaluation folder (Markdown snippets).

Usage: python scripts/results_tables.py [OUT_DIR]   (default out/evaluate)
"""
import json, math, sys
import numpy as np
from pathlib import Path
from mi_bivariate import evaluate as ev
out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path('out/evaluate')
cfg = json.loads((out/'config.json').read_text())
H = cfg['config_hash']; recs = ev.read_records(out/'results.jsonl', H)
rows = ev.summary_rows(recs)
probes = list(dict.fromkeys(r['input_probe'] for r in rows))
def vals(key, p): return [r[key] for r in rows if r['input_probe']==p and key in r and math.isfinite(r[key])]
def med(key, p): v=vals(key,p); return float(np.median(v)) if v else float('nan')
print(f'N={len(recs)} config {H}')
print("\n### medians\n")
print('| input probe | metric | bivariate floor | recovered (bivariate) | GGX fit (3D) | Ward fit (3D) |')
print('|---|---|---:|---:|---:|---:|')
names={'eq1':'Eq. 1','eq1_min':'Eq. 1, f > 1e-3','cosine':'cosine-weighted','log':'log-space'}
for p in probes:
    for m in ('eq1','eq1_min','cosine','log'):
        print(f"| {p} | {names[m]} | {med('floor_'+m,p):.3g} | {med('recovered_'+m,p):.3g} | {med('ggx_'+m,p):.3g} | {med('ward_'+m,p):.3g} |")
print("\n### wins\n")
print('| input probe | metric | recovered < GGX | recovered < Ward | recovered within 2x floor |')
print('|---|---|---:|---:|---:|')
for p in probes:
    sel=[r for r in rows if r['input_probe']==p]
    for m in ('eq1','eq1_min','cosine','log'):
        print(f"| {p} | {names[m]} | {sum(r['recovered_'+m] < r['ggx_'+m] for r in sel)}/{len(sel)} | {sum(r['recovered_'+m] < r['ward_'+m] for r in sel)}/{len(sel)} | {sum(r['recovered_'+m] < 2*r['floor_'+m] for r in sel)}/{len(sel)} |")
for p in probes:
    sel=[r for r in rows if r['input_probe']==p]
    print(p, 'GGX beats bivariate (log):', [r['material'] for r in sel if r['ggx_log'] < r['recovered_log']])
print("\n### images per novel probe (median relative RMSE; floor = ideal bivariate reduction)\n")
novels = list(recs[0]['floor_images'])
print('| input probe | ' + ' | '.join(novels) + ' |'); print('|---|' + '---:|'*len(novels))
for p in probes:
    print(f'| {p} | ' + ' | '.join(f"{np.median([r['inputs'][p]['images'][n]['rel_rmse'] for r in recs]):.3f} ({np.median([r['inputs'][p]['images'][n]['psnr'] for r in recs]):.1f} dB)" for n in novels) + ' |')
print('| floor | ' + ' | '.join(f"{np.median([r['floor_images'][n]['rel_rmse'] for r in recs]):.3f}" for n in novels) + ' |')
print("\n### adequacy\n")
for p in probes:
    a=[r['inputs'][p]['adequacy'] for r in recs]
    print(p, 'rank_fraction median', np.median([x['rank_fraction'] for x in a]), 'adequate', sum(x['adequate'] for x in a), 'reasons', set(sum([x['reasons'] for x in a], [])), 'regions', a[0]['regions'])
print("\n### timing\n")
tot = {}
for r in recs:
    for k,v in r['timings'].items():
        if k!='total': tot['(per material) '+k]=tot.get('(per material) '+k,0)+v
    for p,e in r['inputs'].items():
        for k,v in e['timings'].items(): tot[k]=tot.get(k,0)+v
s=sum(tot.values())
for k,v in sorted(tot.items(), key=lambda x:-x[1]): print(f"| {k} | {v/len(recs):.1f} | {100*v/s:.0f}% |")
print('mean total per material', np.mean([r['timings']['total'] for r in recs]))
print("\n### per material\n")
print(ev.markdown_table(recs))
