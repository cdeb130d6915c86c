"""Diagnosis: where do labels land, Fhat's accuracy on the optimal path vs elsewhere."""
import json, math, sys, time
import gymnasium as gym, numpy as np, torch
import services.sim
from services.learner.runs import learn_hf_policy
from services.learner.evaluation import eval_seeds
torch.set_num_threads(1)
task, method, seed, C = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
env = gym.make(f"services.sim:BrainNav-{task.upper()}-v0", reward_mode="sparse")
u = env.unwrapped; goal = np.array(u._goal)
t = time.time()
hf = learn_hf_policy(env, C, seed, 1000, method=method)
pol = hf.policy
def pos(o):
    return goal - o[10] * np.array([math.cos(o[11]), math.sin(o[11])])
# oracle path states from the evaluation starts' kind of start (reset seed 0 = not an eval start)
path = []
o, _ = env.reset(seed=12345)
for _ in range(60):
    path.append(o.copy()); opt = sorted(u.optimal_actions())
    o, r, term, trunc, info = env.step(opt[0])
    if term: break
P = np.array([pos(p) for p in path]); Y = np.array([p[12] for p in path])
recs = hf.records
on_path = 0
for r in recs:
    ob = np.array(r.obs); d = np.linalg.norm(P - pos(ob), axis=1)
    dy = np.abs((Y - ob[12] + np.pi) % (2*np.pi) - np.pi)
    if np.any((d < 0.31) & (dy < 0.27)): on_path += 1
near = sum(np.min(np.linalg.norm(P - pos(np.array(r.obs)), axis=1)) < 0.31 for r in recs)
# Fhat greedy accuracy along the oracle path and on labelled states
def greedy_ok_at(ob):
    return pol.act(np.asarray(ob, np.float32))
acc_path = []
o, _ = env.reset(seed=12345)
for _ in range(60):
    acc_path.append(pol.act(o) in u.optimal_actions()); o, r, term, trunc, info = env.step(sorted(u.optimal_actions())[0])
    if term: break
# greedy rollouts from eval starts: first error step and best progress
starts = eval_seeds(task, 5)
fails = []
for s0 in starts[:5]:
    o, info = env.reset(seed=s0); L = info["shortest_path_steps"]; first = None; best = L
    for k in range(120):
        a = pol.act(o)
        if first is None and a not in u.optimal_actions(): first = k
        o, r, term, trunc, info = env.step(a)
        c = u.oracle.cost_to_go(*u.pose); best = min(best, c if math.isfinite(c) else best)
        if term: break
    fails.append(dict(first_error=first, best_cost_to_go=float(best), L=L, success=bool(info["is_success"]), steps=k+1))
print(json.dumps(dict(task=task, method=method, seed=seed, C=C, n_episodes=hf.n_episodes,
    labels_on_path_state=on_path, labels_within_0_3m_of_path=int(near),
    greedy_acc_on_path=float(np.mean(acc_path)), path_len=len(acc_path),
    val_acc_true=hf.validation_accuracy_true, rollouts=fails, wall=round(time.time()-t))))
