import json,glob,sys,collections
d=sys.argv[1] if len(sys.argv)>1 else 'sel'
method=sys.argv[2] if len(sys.argv)>2 else 'scone'
rows=collections.defaultdict(dict)
for f in glob.glob(f'{d}/*.json'):
    cfg,scene=f.split('/')[-1][:-5].split('--')
    r=json.load(open(f))
    for s in r['summaries']:
        if s['method']!=method: continue
        n=s['queries']
        rows[cfg][scene]=(round(s['within_025m_2deg']*n),round(s['within_05m_5deg']*n),n,s['landmarks'],s['observations'],s['match_precision'],s['foreign_localised'],s['mean_query_ms'])
scenes=sorted({s for c in rows.values() for s in c})
print('| config | '+' | '.join(scenes)+' | score | foreign |')
for cfg,c in sorted(rows.items(), key=lambda kv: kv[0]):
    score=sum(v[0]+v[1] for v in c.values()); foreign=sum(v[6] for v in c.values())
    print(f'| {cfg} | '+' | '.join(f'{c[s][0]}/{c[s][1]} of {c[s][2]} ({c[s][3]} lm, {c[s][5]:.2f})' if s in c else '-' for s in scenes)+f' | {score} | {foreign} |')
