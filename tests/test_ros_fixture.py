"""The shared in-process ROS fixture really isolates and delivers messages."""
from std_msgs.msg import String


def test_pub_sub_in_one_executor(ros):
    got = []
    pub_node = ros.node('probe_pub')
    sub_node = ros.node('probe_sub')
    pub = pub_node.create_publisher(String, 'chatter', 10)
    sub_node.create_subscription(String, 'chatter', lambda m: got.append(m.data), 10)
    ros.spin_until(lambda: pub.get_subscription_count() > 0, 10.0, 'discovery')
    pub.publish(String(data='hello'))
    ros.spin_until(lambda: got, 5.0, 'message')
    assert got == ['hello']
    assert 1 <= ros.domain_id <= 100
