import subprocess
import sys


def test_lerobot_plugin_discovery_finds_envs_without_importing_the_package():
    code = (
        "from lerobot.utils.import_utils import register_third_party_plugins; register_third_party_plugins();"
        "from lerobot.envs.configs import EnvConfig;"
        "print(sorted(n for n in ('cartpole','acrobot','mountaincar','maze','lunarlander','so101_pickplace',"
        "'metaworld_state') if EnvConfig.get_choice_class(n)))"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr[-2000:]
    assert (
        "['acrobot', 'cartpole', 'lunarlander', 'maze', 'metaworld_state', 'mountaincar', 'so101_pickplace']"
        in result.stdout
    )
