import json,glob,collections
rows=collections.defaultdict(dict)
for f in glob.glob('sel-all/*.json'):
    cfg,scene=f.split('/')[-1][:-5].split('--')
    for s in json.load(open(f))['summaries']:
        n=s['queries']
        rows[(scene,s['method'])][cfg]=(s['landmarks'],s['observations'],s['match_precision'],round(s['within_025m_2deg']*n),round(s['within_05m_5deg']*n),n,s['foreign_localised'])
print('| scene (queries) | method | landmarks / observations, as before | with the known poses | 2D-3D precision, before / with | within (0.25 m, 2°) / (0.5 m, 5°), before / with |')
print('|---|---|---|---|---|---|')
for (scene,m),c in sorted(rows.items()):
    if 'none' not in c or 'build' not in c: continue
    a,b=c['none'],c['build']
    print(f"| {scene} ({a[5]}) | {m} | {a[0]:,} / {a[1]:,} | {b[0]:,} / {b[1]:,} | {a[2]:.3f} / {b[2]:.3f} | {a[3]}/{a[4]} / {b[3]}/{b[4]} |")
