import json,os,sys
proto=sys.argv[1]  # far or sparse
scenes={'far':['kitti-clip2','middlebury-dino48','strecha-fountain-P11','tum-fr3-long-office'],
        'sparse':['kitti-clip2','middlebury-dino48','tum-fr3-long-office']}[proto]
def summ(path, method):
    r=json.load(open(path))
    for s in r['summaries']:
        if s['method']==method: return s
print('| scene (queries) | method | landmarks | old (0.25 m, 2°) | **new** (0.25 m, 2°) | old (0.5 m, 5°) | new (0.5 m, 5°) | 2D-3D precision old / new | foreign frames localised, old / new |')
print('|---|---|---|---|---|---|---|---|---|')
for sc in scenes:
    for m,name in [('scone','SConE'),('freak','FREAK'),('sift','SIFT')]:
        old=summ(f'val/{proto}-{sc}-old.json',m)
        nf=f'val/{proto}-{sc}-new-freak.json'
        new=summ(nf if m=='freak' and os.path.exists(nf) else f'val/{proto}-{sc}-new.json',m)
        n=old['queries']
        c=lambda s,k: round(s[k]*n)
        print(f"| {sc} ({n}) | {name} | {old['landmarks'] if proto=='sparse' else old['landmarks']-0:,} | {c(old,'within_025m_2deg')} | **{c(new,'within_025m_2deg')}** | {c(old,'within_05m_5deg')} | {c(new,'within_05m_5deg')} | {old['match_precision']:.3f} / {new['match_precision']:.3f} | {old['foreign_localised']}/{old['foreign_queries']} / {new['foreign_localised']}/{new['foreign_queries']} |")
