"""TF-Agents' "Train a Deep Q Network" tutorial (DQN on CartPole-v0), run as a benchmark peer.

What it is: the training part of https://www.tensorflow.org/agents/tutorials/1_dqn_tutorial
(tensorflow/agents docs/tutorials/1_dqn_tutorial.ipynb), kept as the tutorial writes it, on CPU,
with a seed, a thread limit and a JSON result added. It is a benchmark peer only: TensorFlow,
TF-Agents and Reverb are never dependencies of relayrl, and this file is never imported by it.

Setup (its own venv, outside the repo; the same commands are in bench/setup_tfagents.sh):

    python3.11 -m venv /work/benchvenv-tfa
    /work/benchvenv-tfa/bin/pip install --upgrade pip
    /work/benchvenv-tfa/bin/pip install "tensorflow-cpu==2.15.1" "tf-keras==2.15.0" \\
        "tensorflow-probability==0.23.0" "dm-reverb==0.14.0" "gym==0.23.0" "pygame==2.1.3" \\
        "numpy<2" "typing-extensions==4.5.0" absl-py cloudpickle gin-config pillow six protobuf wrapt
    /work/benchvenv-tfa/bin/pip install --no-deps "tf-agents==0.19.0"

  tf-agents goes in with --no-deps because its `[reverb]` extra asks for the `tensorflow` wheel
  (about twice the size of `tensorflow-cpu`, same code); every other requirement of tf-agents 0.19.0
  is installed by the line above it, so `pip check` is clean. gym is 0.23.0 because tf-agents
  declares gym<=0.23.0. pygame is needed although nothing is rendered: gym 0.23's cartpole.py
  imports it at module level.

Run:

    /work/benchvenv-tfa/bin/python bench/tfagents_dqn_tutorial.py --seed 0 [--iterations 20000]
        [--eval-interval 1000] [--threads 1] [--json out.json]

The tutorial's hyperparameters: CartPole-v0 via suite_gym, Q-net Dense(100)-Dense(50) ReLU with
VarianceScaling(2.0, fan_in, truncated_normal) kernels, Q head RandomUniform(-0.03, 0.03) kernel and
Constant(-0.2) bias, Adam(1e-3), element_wise_squared_loss, DqnAgent defaults otherwise (epsilon 0.1,
gamma 1.0, hard target update every step, n-step 1, no gradient clipping); Reverb table of 100,000
items (Uniform sampler, Fifo remover, MinSize(1)), ReverbAddTrajectoryObserver with sequence_length 2;
100 random steps with PyDriver; dataset batch 64, num_steps 2, num_parallel_calls 3, prefetch(3);
per iteration 1 collect step (PyDriver, collect policy) and 1 gradient step (agent.train wrapped in
common.function); greedy evaluation over 10 episodes before training and every 1,000 iterations.
Note that in this stack the 200-step time limit ends an episode with discount 0 (gym's own TimeLimit
sets done and GymWrapper turns done into a termination).

As in the tutorial, both drivers step the first environment the tutorial loads (`env`, which the
tutorial resets and steps once with action 1 while showing the API), starting from a time step of
`train_py_env.reset()`; the illustrative cells that only print, render or evaluate the random
policy are left out.

Added, not in the tutorial:
  --seed S         seeds Python `random`, NumPy, `tf.random.set_seed(S)` and the three gym envs
                   through their old-gym `seed()` (env S, train_py_env S+1, eval_py_env S+2). Reverb's
                   uniform sampler has its own unseeded RNG, so runs are not bit-for-bit repeatable.
  --threads N      tf.config.threading intra- and inter-op threads (default 1). tf.data's and Reverb's
                   own thread pools are not covered by it.
  --json PATH      {"seed", "iterations", "evals": [[iteration, avg_return], ...], "train_seconds",
                   "eval_seconds"}. train_seconds: wall-clock of the 100 random steps plus the training
                   loop (tf.function tracing included), evaluations excluded; eval_seconds: all
                   evaluations, the one before training included.
The tutorial's loss print every 200 steps is off unless --log-interval N is given; one line is printed
per evaluation.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import sys
import time

os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--iterations", type=int, default=20000)
    p.add_argument("--eval-interval", type=int, default=1000)
    p.add_argument("--eval-episodes", type=int, default=10)
    p.add_argument("--log-interval", type=int, default=0, help="loss print period (tutorial: 200; 0 = off)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--json", default=None)
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)

    import numpy as np
    import reverb
    import tensorflow as tf

    # Before any op runs: the thread pools are fixed at the first one.
    tf.config.threading.set_intra_op_parallelism_threads(args.threads)
    tf.config.threading.set_inter_op_parallelism_threads(args.threads)

    from tf_agents.agents.dqn import dqn_agent
    from tf_agents.drivers import py_driver
    from tf_agents.environments import suite_gym, tf_py_environment
    from tf_agents.networks import sequential
    from tf_agents.policies import py_tf_eager_policy, random_tf_policy
    from tf_agents.replay_buffers import reverb_replay_buffer, reverb_utils
    from tf_agents.specs import tensor_spec
    from tf_agents.utils import common

    random.seed(args.seed)
    np.random.seed(args.seed)
    tf.random.set_seed(args.seed)

    # Hyperparameters (tutorial values).
    num_iterations = args.iterations
    initial_collect_steps = 100
    collect_steps_per_iteration = 1
    replay_buffer_max_length = 100000
    batch_size = 64
    learning_rate = 1e-3
    log_interval = args.log_interval
    num_eval_episodes = args.eval_episodes
    eval_interval = args.eval_interval

    # Environment.
    env_name = "CartPole-v0"
    env = suite_gym.load(env_name)
    env.seed(args.seed)
    env.reset()
    env.step(np.array(1, dtype=np.int32))  # the tutorial's API demo step on `env`

    train_py_env = suite_gym.load(env_name)
    eval_py_env = suite_gym.load(env_name)
    train_py_env.seed(args.seed + 1)
    eval_py_env.seed(args.seed + 2)
    train_env = tf_py_environment.TFPyEnvironment(train_py_env)
    eval_env = tf_py_environment.TFPyEnvironment(eval_py_env)

    # Agent.
    fc_layer_params = (100, 50)
    action_tensor_spec = tensor_spec.from_spec(env.action_spec())
    num_actions = action_tensor_spec.maximum - action_tensor_spec.minimum + 1

    def dense_layer(num_units):
        return tf.keras.layers.Dense(
            num_units,
            activation=tf.keras.activations.relu,
            kernel_initializer=tf.keras.initializers.VarianceScaling(
                scale=2.0, mode="fan_in", distribution="truncated_normal"))

    dense_layers = [dense_layer(num_units) for num_units in fc_layer_params]
    q_values_layer = tf.keras.layers.Dense(
        num_actions,
        activation=None,
        kernel_initializer=tf.keras.initializers.RandomUniform(minval=-0.03, maxval=0.03),
        bias_initializer=tf.keras.initializers.Constant(-0.2))
    q_net = sequential.Sequential(dense_layers + [q_values_layer])

    optimizer = tf.keras.optimizers.Adam(learning_rate=learning_rate)
    train_step_counter = tf.Variable(0)
    agent = dqn_agent.DqnAgent(
        train_env.time_step_spec(),
        train_env.action_spec(),
        q_network=q_net,
        optimizer=optimizer,
        td_errors_loss_fn=common.element_wise_squared_loss,
        train_step_counter=train_step_counter)
    agent.initialize()

    random_policy = random_tf_policy.RandomTFPolicy(train_env.time_step_spec(), train_env.action_spec())

    def compute_avg_return(environment, policy, num_episodes=10):
        total_return = 0.0
        for _ in range(num_episodes):
            time_step = environment.reset()
            episode_return = 0.0
            while not time_step.is_last():
                action_step = policy.action(time_step)
                time_step = environment.step(action_step.action)
                episode_return += time_step.reward
            total_return += episode_return
        avg_return = total_return / num_episodes
        return avg_return.numpy()[0]

    # Replay buffer (Reverb).
    table_name = "uniform_table"
    replay_buffer_signature = tensor_spec.from_spec(agent.collect_data_spec)
    replay_buffer_signature = tensor_spec.add_outer_dim(replay_buffer_signature)
    table = reverb.Table(
        table_name,
        max_size=replay_buffer_max_length,
        sampler=reverb.selectors.Uniform(),
        remover=reverb.selectors.Fifo(),
        rate_limiter=reverb.rate_limiters.MinSize(1),
        signature=replay_buffer_signature)
    reverb_server = reverb.Server([table])
    replay_buffer = reverb_replay_buffer.ReverbReplayBuffer(
        agent.collect_data_spec,
        table_name=table_name,
        sequence_length=2,
        local_server=reverb_server)
    rb_observer = reverb_utils.ReverbAddTrajectoryObserver(
        replay_buffer.py_client, table_name, sequence_length=2)

    eval_seconds = 0.0
    t_start = time.perf_counter()

    # Data collection: 100 random steps.
    py_driver.PyDriver(
        env,
        py_tf_eager_policy.PyTFEagerPolicy(random_policy, use_tf_function=True),
        [rb_observer],
        max_steps=initial_collect_steps).run(train_py_env.reset())

    dataset = replay_buffer.as_dataset(
        num_parallel_calls=3, sample_batch_size=batch_size, num_steps=2).prefetch(3)
    iterator = iter(dataset)

    # Training (the tutorial's loop).
    agent.train = common.function(agent.train)
    agent.train_step_counter.assign(0)

    t0 = time.perf_counter()
    avg_return = compute_avg_return(eval_env, agent.policy, num_eval_episodes)
    eval_seconds += time.perf_counter() - t0
    evals = [[0, float(avg_return)]]
    print(f"step = {0}: Average Return = {avg_return}", flush=True)

    time_step = train_py_env.reset()
    collect_driver = py_driver.PyDriver(
        env,
        py_tf_eager_policy.PyTFEagerPolicy(agent.collect_policy, use_tf_function=True),
        [rb_observer],
        max_steps=collect_steps_per_iteration)

    for _ in range(num_iterations):
        time_step, _ = collect_driver.run(time_step)
        experience, unused_info = next(iterator)
        train_loss = agent.train(experience).loss
        step = agent.train_step_counter.numpy()

        if log_interval and step % log_interval == 0:
            print(f"step = {step}: loss = {train_loss}", flush=True)

        if step % eval_interval == 0:
            t0 = time.perf_counter()
            avg_return = compute_avg_return(eval_env, agent.policy, num_eval_episodes)
            eval_seconds += time.perf_counter() - t0
            evals.append([int(step), float(avg_return)])
            elapsed = time.perf_counter() - t_start
            print(f"step = {step}: Average Return = {avg_return}  (elapsed {elapsed:.1f}s, eval {eval_seconds:.1f}s)",
                  flush=True)

    total = time.perf_counter() - t_start
    train_seconds = total - eval_seconds
    print(f"train {train_seconds:.1f}s  eval {eval_seconds:.1f}s  total {total:.1f}s", flush=True)

    rb_observer.close()
    reverb_server.stop()

    if args.json:
        with open(args.json, "w") as f:
            json.dump({"seed": args.seed, "iterations": num_iterations, "evals": evals,
                       "train_seconds": train_seconds, "eval_seconds": eval_seconds}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
