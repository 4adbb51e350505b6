import time, dataclasses, numpy as np, jaxwear as jw
from jaxwear.diagnose import Model
from jaxwear.effects.law import searching, LawSpec, Term
from jaxwear._residual import traces
res = jw.synthesize([], "paper", noise_um=0.3, seed=2, numerics=dict(nodes=48, steps_per_rev=48, revolutions_per_update=500))
study = res.study.with_experiments(res.study.experiments[:2])
base = Model(study, candidates=[])
print(base.keys)
allkeys = ["law_gain","law_deposit","law_a_1","law_x0_1","law_w_1","law_b_1","law_a_2","law_x0_2","law_w_2","law_b_2"]
with searching():
    for law in [LawSpec("factor",(Term("hinge","pressure_MPa",1.0,a=1,x0=0.5),),0.5),
                LawSpec("deposit",(Term("power","load_turn_rate_deg_per_s",1000.0,a=2),Term("step","load_N",100.,x0=1,w=0.1)),0.01),
                LawSpec("factor",(Term("power","worn_depth_um",5.0,a=1),),0.3)]:
        st = dataclasses.replace(study, config=study.config.replace(effects=study.config.effects+("law_search",)),
                                 parameters={**study.parameters, **{k:v for k,v in law.values().items() if k not in allkeys}})
        t=time.time()
        m = Model(st, keys=base.keys+allkeys, candidates=[], start={k:v for k,v in law.values().items() if k in allkeys})
        ev = m.evaluate(np.zeros(len(m.names)))
        print(law.label, time.time()-t, traces(), float(np.abs(ev.pred).max()), np.abs(ev.J).max(axis=0).round(3))
    print(base.evaluate(np.zeros(len(base.names))).pred.max())
