//! A lab test's record on the broker (`<topic>/labtest/<id>`, retained; the message and its
//! checks are the wire contract's, `tagdeflect_wire::lab_test`): kept to publish again on every
//! connection, and waited for at the end of a run.

use rumqttc::QoS;

use super::state::{Sent, Shared, State};
use super::MqttPublisher;
use tagdeflect_core::lab_test::TestRecord;
use tagdeflect_wire::{LabTestMessage, LAB_TEST_SUFFIX, MAX_LAB_TEST_BYTES};

/// A lab test's record to keep on the broker.
#[derive(Debug)]
pub(super) struct LabOut {
    pub(super) id: String,
    pub(super) payload: Vec<u8>,
    /// The serial number of its latest publish.
    pub(super) serial: u64,
    /// The broker acknowledged its latest version.
    pub(super) delivered: bool,
}

/// Lab test records kept to send again on every connection (the newest; a day has a dozen).
const LAB_RECORDS: usize = 64;

impl MqttPublisher {
    /// Publishes a lab test's record, retained, on `<topic>/labtest/<id>` (now if connected,
    /// else on connecting; again on every connection); never blocks.
    pub fn publish_lab_test(&self, record: &TestRecord) {
        let msg = LabTestMessage::from_record(&self.shared().rig, self.test(), record);
        let payload = serde_json::to_vec(&msg).expect("a lab test record serialises");
        if payload.len() > MAX_LAB_TEST_BYTES {
            tracing::warn!(test = %record.id, bytes = payload.len(), "MQTT: the lab test record is larger than an archive takes; sent anyway");
        }
        let mut st = self.shared().state.lock().expect("mqtt state");
        let i = match st.lab.iter().position(|l| l.id == record.id) {
            Some(i) => i,
            None => {
                st.lab.push(LabOut { id: record.id.clone(), payload: Vec::new(), serial: 0, delivered: false });
                st.lab.len() - 1
            }
        };
        st.lab[i].payload = payload;
        st.lab[i].delivered = false;
        let id = record.id.clone();
        while st.lab.len() > LAB_RECORDS {
            match st.lab.iter().position(|l| l.delivered) {
                Some(j) => {
                    st.lab.remove(j);
                }
                None => break,
            }
        }
        if let Some(i) = st.lab.iter().position(|l| l.id == id) {
            self.shared().send_lab(&mut st, i);
        }
    }
}

impl Shared {
    /// Hands the `i`-th lab record to the client when connected.
    pub(super) fn send_lab(&self, st: &mut State, i: usize) {
        if !st.connected {
            return;
        }
        st.lab_serial += 1;
        let serial = st.lab_serial;
        let l = &mut st.lab[i];
        let topic = format!("{}/{}/{}", self.base_topic, LAB_TEST_SUFFIX, l.id);
        if self.client.try_publish(topic, QoS::AtLeastOnce, true, l.payload.clone()).is_ok() {
            l.serial = serial;
            st.order.push_back(Sent::Lab(serial));
        }
    }
}
