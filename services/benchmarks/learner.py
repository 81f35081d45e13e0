"""``ra2vipas bench learner``: the POD learner scored on each seed's training episode."""

from __future__ import annotations


def learner(preset: str, seeds: list[int]) -> dict:
    """Per seed: R², the RMSE against the POD the RSSI predicts p*(r), the oracle fit's RMSE,
    their ratio and the training time; and whether every RMSE is within 1.3 x the oracle's."""
    from ra2vipas.services.learner.pod import LearnerSettings, fit_pod, score_pod
    from ra2vipas.services.protocol.scenario import build_scenario
    from ra2vipas.services.sensors.world import TrainingEpisode

    scenario = build_scenario(preset)
    rows = []
    for seed in seeds:
        episode = TrainingEpisode(scenario, seed)
        learned = fit_pod(list(episode.samples()), LearnerSettings.for_scenario(scenario))
        truth = episode.truth
        score = score_pod(learned.model, truth.rssi_dbm, truth.pod, truth.pod_at_range)
        rows.append({"seed": seed, "r2": round(score.r2, 4), "rmse": round(score.rmse, 4), "oracle_rmse": round(score.oracle_rmse, 4),
                     "ratio": round(score.rmse / max(score.oracle_rmse, 1e-9), 3), "train_seconds": round(learned.train_seconds, 3)})
    return {"benchmark": "learner", "preset": preset, "seeds": rows,
            "within_1_3x_oracle": all(r["rmse"] <= 1.3 * r["oracle_rmse"] for r in rows)}
